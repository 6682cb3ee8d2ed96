"""Run a command while busy processes keep every core loaded: how CI behaves on a shared machine.

``make test-stress`` runs the test suite this way (``python bench/cpu_hog.py -- CMD ...``).
The hogs run at the same priority as the command (a shared CI runner does not nice its
neighbours), stop when the command ends, and the command's exit status is returned. The
load average seen during the run is printed at the end.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import signal
import subprocess
import sys
import time


def burn() -> None:
    """Spin until killed."""
    x = 0
    while True:
        x = (x * 1103515245 + 12345) & 0xFFFFFFFF


def main(argv: list[str] | None = None) -> int:
    """Start the hogs, run the command, stop the hogs; exit with the command's status."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 2,
                        help="busy processes (default: one per core)")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- then the command to run")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("give the command to run after --")
    if args.workers < 0:
        parser.error("--workers must be >= 0")
    hogs = [multiprocessing.Process(target=burn, daemon=True) for _ in range(args.workers)]
    for h in hogs:
        h.start()
    began = time.monotonic()
    print(f"cpu_hog: {args.workers} busy processes; running {' '.join(command)}", file=sys.stderr, flush=True)
    try:
        code = subprocess.call(command)
    except KeyboardInterrupt:
        code = 130
    finally:
        load = os.getloadavg()
        for h in hogs:
            if h.pid is not None:
                os.kill(h.pid, signal.SIGKILL)
        for h in hogs:
            h.join(timeout=5)
    print(f"cpu_hog: the command exited {code} after {time.monotonic() - began:.0f} s; "
          f"load average at the end {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}", file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main())
