#!/usr/bin/env python3
"""Long fuzzing run of every parser the tests fuzz briefly: compass NMEA and OS5000 lines, ODrive
and VESC frames, the LCM receive path (tests/fuzz_targets.py), and the GPS driver (bench/fuzz_gps.py).

Each target runs in a process of its own for ``--seconds``, through the real driver code,
with one of two engines:

- ``atheris`` (coverage-guided, libFuzzer) when it is installed (``pip install atheris``;
  ``make fuzz`` tries), seeded with the target's corpus of valid inputs; for NMEA the
  input is also tried with its checksum recomputed, so the fields are reached;
- the seeded mutator of tests/fuzz_targets.py otherwise, or with ``--engine seeded``.

A failure -- an exception escaping a parser, or a published value that is not finite or out
of range -- prints its traceback, writes the input to ``fuzz-<target>-failure.bin`` and
makes the exit status 1. With atheris, libFuzzer prints its statistics and ends the
target's process itself (exit status 0 when it found nothing).

Usage: ``python bench/fuzz.py [--seconds 60] [--engine auto|atheris|seeded] [--only TARGET ...]``
(targets: compass-nmea, compass-os5000, odrive, vesc, lcm, gps). Not a test: it prints.
"""

from __future__ import annotations

import argparse
import logging
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

from u2sa_hw.bus.run_keys import use_run_key  # noqa: E402
from u2sa_hw.bus.udp_ports import private_lcm_url  # noqa: E402

GPS_SCRIPT = REPO / "bench" / "fuzz_gps.py"
ALL = ("compass-nmea", "compass-os5000", "odrive", "vesc", "lcm", "gps")


def have_atheris() -> bool:
    try:
        import atheris  # noqa: F401, PLC0415 - optional
    except ImportError:
        return False
    return True


def failure(name: str, data: bytes) -> int:
    traceback.print_exc()
    path = Path(f"fuzz-{name}-failure.bin")
    path.write_bytes(data)
    print(f"{name}: FAILED; the input is in {path}")
    return 1


def child(name: str, seconds: float, engine: str, seed: int) -> int:
    """Run one target in this process (its drivers' own error reports are silenced: the fuzz makes many)."""
    logging.disable(logging.ERROR)
    import fuzz_targets as ft  # noqa: PLC0415 - after use_run_key
    if engine == "atheris":
        import atheris  # noqa: PLC0415 - optional

        atheris.instrument_all()   # coverage of every module loaded: the drivers, the protocols, the decoders

    with tempfile.TemporaryDirectory() as tmp:
        target = ft.make_target(name, workdir=Path(tmp), lcm_url=private_lcm_url())
        start = time.monotonic()
        runs = 0
        try:
            if engine == "seeded":
                mutator = ft.Mutator(target.corpus, seed=seed, nmea=target.nmea)
                for data in target.corpus:
                    target.run(data)
                while time.monotonic() - start < seconds:
                    for _ in range(1000):
                        data = mutator.next()
                        try:
                            target.run(data)
                        except ft.FuzzViolation:
                            return failure(name, data)
                    runs += 1000
            else:
                runs = _atheris(ft, target, name, seconds, Path(tmp))
        finally:
            target.close()
        elapsed = time.monotonic() - start
        print(f"{name}: engine {engine}, {runs} inputs in {elapsed:.0f} s ({runs / max(elapsed, 1e-9):.0f}/s), "
              f"no failure; {_summary(target)}")
    return 0


def _atheris(ft: object, target: object, name: str, seconds: float, workdir: Path) -> int:
    import atheris  # noqa: PLC0415 - optional

    runs = [0]

    def one_input(data: bytes) -> None:
        runs[0] += 1
        inputs = [data, ft.fix_checksum(data)] if target.nmea else [data]  # type: ignore[attr-defined]
        for item in inputs:
            try:
                target.run(item)  # type: ignore[attr-defined]
            except ft.FuzzViolation:  # type: ignore[attr-defined]
                failure(name, item)
                raise

    corpus = workdir / "corpus"
    corpus.mkdir()
    for k, data in enumerate(target.corpus):  # type: ignore[attr-defined]
        (corpus / f"seed{k}").write_bytes(data)
    argv = [sys.argv[0], f"-max_total_time={int(seconds)}", "-max_len=512", "-print_final_stats=1", str(corpus)]
    atheris.Setup(argv, one_input)
    try:
        atheris.Fuzz()
    except SystemExit:
        pass
    return runs[0]


def _summary(target: object) -> str:
    driver = getattr(target, "driver", None) or getattr(target, "svc", None)
    if driver is None:
        return "decode and signature check only"
    details = driver.health_details()
    kinds = details.get("out_of_range_kinds") or "none"
    dropped = f"{details.get('out_of_range', 0)} impossible values dropped ({kinds})"
    counted = ", ".join(f"{k} {details[k]}" for k in ("published", "malformed", "bad_checksums", "dropped",
                                                      "odometry_published") if k in details)
    return f"{dropped}; {counted}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="per target (default 60)")
    parser.add_argument("--engine", choices=("auto", "atheris", "seeded"), default="auto",
                        help="atheris when installed (auto), or the seeded mutator")
    parser.add_argument("--seed", type=int, default=1, help="seed of the seeded mutator")
    parser.add_argument("--only", nargs="+", choices=ALL, help="run these targets only")
    parser.add_argument("--child", choices=ALL[:-1], help=argparse.SUPPRESS)
    args = parser.parse_args()
    engine = args.engine
    if engine in ("auto", "atheris") and not have_atheris():
        if engine == "atheris":
            print("atheris is not installed (pip install atheris)", file=sys.stderr)
            return 2
        print("atheris is not installed: using the seeded mutator")
        engine = "seeded"
    elif engine == "auto":
        engine = "atheris"
    use_run_key()   # without an installed bus key, a fresh one for this run and its children
    if args.child:
        return child(args.child, args.seconds, engine, args.seed)
    status = 0
    for name in args.only or ALL:
        if name == "gps":
            if not GPS_SCRIPT.exists():
                print("gps: bench/fuzz_gps.py is not there; skipped")
                continue
            cmd = [sys.executable, str(GPS_SCRIPT), "--seconds", str(args.seconds), "--engine", engine,
                   "--seed", str(args.seed)]
        else:
            cmd = [sys.executable, __file__, "--child", name, "--seconds", str(args.seconds), "--engine", engine,
                   "--seed", str(args.seed)]
        print(f"--- {name} ({args.seconds:g} s, {engine})", flush=True)
        code = subprocess.run(cmd, check=False).returncode
        if code:
            print(f"{name}: exit status {code}")
            status = 1
    print("all targets passed" if status == 0 else "FAILURES above")
    return status


if __name__ == "__main__":
    sys.exit(main())
