#!/usr/bin/env python3
"""Long fuzzing run of the GPS NMEA driver (the bounded one is tests/test_gps_fuzz.py in ``make test``).

Two engines, both feeding the real driver class (``u2sa_hw.drivers.gps_nmea.driver.GpsNmeaDriver``,
GEODETIC frame, publishing over LCM on a private local bus; ``bench/fuzz.py`` runs it as
its ``gps`` target) and checking every message
it publishes (finite, latitude/longitude/altitude/speed/sigmas in range):

- ``atheris`` (coverage-guided, libFuzzer) when it is installed (``pip install atheris``;
  a wheel exists for CPython 3.11 on x86-64 Linux). Each input is a few lines; the
  fuzzer's bytes are used as they are and also, with the checksum recomputed, so most
  inputs get past the checksum to the field parsing.
- the seeded mutator of tests/gps_fuzzing.py (bit flips, digit inflation, field
  deletion/duplication/swap, truncation, recomputed checksums) otherwise, or with
  ``--engine seeded``.

Usage: ``python bench/fuzz_gps.py [--seconds 300] [--engine auto|atheris|seeded] [--seed N]``.
The seeded engine prints the inputs run, messages published and values dropped by kind;
atheris prints libFuzzer's statistics (it ends the process itself). Any failure prints its
traceback and writes the input that caused it to ``fuzz-gps-failure.bin`` (exit status not 0).
"""

from __future__ import annotations

import argparse
import random
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

from gps_fuzzing import check_message, feed, fuzz_cases, seed_line  # noqa: E402

from u2sa_hw.drivers.gps_nmea.driver import GpsNmeaDriver  # noqa: E402
from u2sa_hw import lcmtypes as t  # noqa: E402
from u2sa_hw.bus.run_keys import use_run_key  # noqa: E402
from u2sa_hw.bus.transport import Transport  # noqa: E402
from u2sa_hw.profile.vehicle import VehicleProfile  # noqa: E402
from u2sa_hw.bus.udp_ports import private_lcm_url  # noqa: E402


class CheckedGps(GpsNmeaDriver):
    """The real driver; every message it publishes is checked before it goes out."""

    def publish_state(self, msg: t.StateInformation) -> bool:
        check_message(msg)
        self.checked = getattr(self, "checked", 0) + 1
        return super().publish_state(msg)


def make_driver(workdir: Path, transport: Transport) -> CheckedGps:
    profile = VehicleProfile(path=None, devices={"gps": {"address": "serial:///dev/u2sa/gps?baud=9600"}})
    return CheckedGps("gps", profile=profile, config_path=workdir / "gps.toml", transport=transport,
                      settings={"position_frame": "GEODETIC", "altitude_datum": "ellipsoid"})


def with_checksums(data: bytes) -> list[bytes]:
    """*data* split into lines, each also given a correct checksum (so the fields get parsed)."""
    out = []
    for raw in data.split(b"\n")[:16]:
        out.append(raw + b"\n")
        body = raw.strip().lstrip(b"$").split(b"*", 1)[0]
        value = 0
        for byte in body:
            value ^= byte
        out.append(b"$" + body + f"*{value:02X}\r\n".encode())
    return out


def report(driver: CheckedGps, inputs: int, elapsed: float, engine: str) -> None:
    details: dict[str, Any] = driver.health_details()
    print(f"engine {engine}: {inputs} inputs in {elapsed:.1f} s ({inputs / max(elapsed, 1e-9):.0f}/s); "
          f"{getattr(driver, 'checked', 0)} messages published and checked; "
          f"{details['out_of_range']} values dropped ({details['out_of_range_kinds'] or 'none'}); "
          f"{details['malformed']} malformed, {details['bad_checksums']} bad checksums")


def run_seeded(seconds: float, seed: int, workdir: Path, transport: Transport) -> int:
    driver = make_driver(workdir, transport)
    start = time.monotonic()
    inputs = 0
    while time.monotonic() - start < seconds:
        rng = random.Random(seed + inputs)
        cases = fuzz_cases(rng, 500)
        try:
            feed(driver.handle_line, driver.handle_idle, rng, cases)
        except Exception:  # noqa: BLE001 - a failure is the finding: report it with its input
            traceback.print_exc()
            Path("fuzz-gps-failure.bin").write_bytes(b"".join(cases))
            print(f"FAILED with seed {seed + inputs} (500 lines written to fuzz-gps-failure.bin)")
            return 1
        inputs += len(cases)
    report(driver, inputs, time.monotonic() - start, "seeded")
    return 0


def run_atheris(seconds: float, workdir: Path, transport: Transport) -> int:
    import atheris  # noqa: PLC0415 - optional

    driver = make_driver(workdir, transport)
    counter = {"inputs": 0, "start": time.monotonic()}

    def one_input(data: bytes) -> None:
        counter["inputs"] += 1
        clock = 1000.0 + counter["inputs"]
        try:
            for k, line in enumerate(with_checksums(data)):
                driver.handle_line(line, clock + k * 0.01)
            driver.handle_idle()
        except Exception:
            Path("fuzz-gps-failure.bin").write_bytes(data)
            raise

    corpus = workdir / "corpus"   # seeds: valid epochs of every sentence kind, so mutation starts from NMEA
    corpus.mkdir()
    rng = random.Random(1)
    for k in range(64):
        (corpus / f"seed{k}").write_bytes(b"".join(seed_line(rng) for _ in range(rng.randint(1, 6))))
    argv = [sys.argv[0], f"-max_total_time={int(seconds)}", "-max_len=1024", "-print_final_stats=1", str(corpus)]
    atheris.instrument_all()   # coverage of every module loaded: the driver, pynmeagps, the fix logic
    atheris.Setup(argv, one_input)
    try:
        atheris.Fuzz()
    except SystemExit:
        pass
    report(driver, counter["inputs"], time.monotonic() - counter["start"], "atheris")
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=300.0, help="how long to run (default 300)")
    parser.add_argument("--engine", choices=("auto", "atheris", "seeded"), default="auto",
                        help="atheris when installed (auto), or the seeded mutator")
    parser.add_argument("--seed", type=int, default=1, help="first seed of the seeded mutator")
    args = parser.parse_args()
    engine = args.engine
    if engine in ("auto", "atheris"):
        try:
            import atheris  # noqa: F401, PLC0415
            engine = "atheris"
        except ImportError:
            if engine == "atheris":
                print("atheris is not installed (pip install atheris)", file=sys.stderr)
                return 2
            print("atheris is not installed: using the seeded mutator")
            engine = "seeded"
    use_run_key()   # without an installed bus key, a fresh one for this run
    transport = Transport(private_lcm_url(), name="fuzz-gps")   # a bus of its own: nobody listens
    try:
        with tempfile.TemporaryDirectory() as tmp:
            if engine == "atheris":
                return run_atheris(args.seconds, Path(tmp), transport)
            return run_seeded(args.seconds, args.seed, Path(tmp), transport)
    finally:
        transport.stop()


if __name__ == "__main__":
    sys.exit(main())
