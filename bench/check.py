"""How long ``u2sa check`` takes: the offline check of each example, and ``--probe`` against its mocks.

    python bench/check.py                 # offline, every example, in this process
    python bench/check.py --probe 2       # also u2sa mock of each example and a probe with a 2 s window

The offline figure is the median of --repeat runs of ``check_profile`` (the first run,
which imports every service kind, is shown apart). The probe figure is the wall time of
``probe_profile`` over every device of the profile ``u2sa mock`` writes; the devices are
probed at once, so it is about one window.
"""

from __future__ import annotations

import argparse
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))


def offline(example: Path, repeat: int) -> tuple[float, float, int]:
    """(first run s, median of the rest s, problems) of check_profile on *example*."""
    from u2sa_hw.check import check_profile

    times, problems = [], []
    for _ in range(repeat + 1):
        t = time.perf_counter()
        problems = check_profile(example, for_sim=True)
        times.append(time.perf_counter() - t)
    return times[0], statistics.median(times[1:]), len(problems)


def probe(example: Path, seconds: float, run_dir: Path) -> tuple[float, int, int]:
    """(wall s, devices, failed) of probe_profile against ``u2sa mock`` of *example*."""
    from u2sa_hw.check.probe import probe_profile
    from u2sa_hw.bus.udp_ports import private_udp_port
    from u2sa_hw.profile.loader import load_profile

    proc = subprocess.Popen([sys.executable, "-m", "u2sa_hw.cli", "mock", "--vehicle", str(example), "--run-dir",
                             str(run_dir), "--can-port", str(private_udp_port(span=2))], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, text=True)
    try:
        assert proc.stdout is not None
        sim = next(line.split(": ", 1)[1].strip() for line in proc.stdout if line.startswith("simulation profile: "))
        t = time.perf_counter()
        results = probe_profile(load_profile(sim), seconds=seconds)
        return time.perf_counter() - t, len(results), sum(not r.ok for r in results)
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=20)


def main(argv: list[str] | None = None) -> int:
    """Print the figures, one line per example."""
    import tempfile

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=5, help="offline runs after the first (default 5)")
    parser.add_argument("--probe", type=float, metavar="S", help="also probe the mocks with an S-second window")
    args = parser.parse_args(argv)
    for example in sorted((REPO / "examples").glob("*/vehicle.toml")):
        first, median, count = offline(example, args.repeat)
        line = f"{example.parent.name:16} offline: first {first * 1000:6.0f} ms, then {median * 1000:5.0f} ms " \
               f"({count} problems for sim)"
        if args.probe:
            with tempfile.TemporaryDirectory(prefix="u2sa-bench-check-") as tmp:
                wall, devices, failed = probe(example, args.probe, Path(tmp))
            line += f"; probe: {devices} devices, {failed} failed, {wall:.2f} s wall ({args.probe:g} s window)"
        print(line, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
