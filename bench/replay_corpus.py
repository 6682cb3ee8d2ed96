"""``u2sa replay-check`` over the test corpus of recordings (tests/replay_corpus.py: both example vehicles
and the boat, the sticks scenario, an RC loss, a GPS fix loss, a manual switch, a driver restarted
mid-recording, recordings started while the stack drives, one cut by SIGKILL and recovered, u2sa record of
a u2sa mock + u2sa run stack), while
``bench/cpu_hog.py`` keeps every core busy (issue 24: "replay-check over that corpus is clean under
cpu_hog"). The corpus is built first, on the quiet machine; the verdicts are printed, with the build
and check times.

    python bench/replay_corpus.py [--keep DIR] [--edge N] [--workers N]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# not bench/ itself: bench/drivers.py would stand in for the drivers package (issue 25, one namespace)
sys.path[0:1] = [str(REPO), str(REPO / "tests")]

from replay_corpus import build_corpus  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--keep", type=Path, help="build the corpus here and keep it")
    ap.add_argument("--edge", default="1", help="replay-check --edge (default 1, replay-check's own, as the tests)")
    ap.add_argument("--workers", default=None, help="cpu_hog --workers (default: one per core)")
    args = ap.parse_args()
    root = args.keep or Path(tempfile.mkdtemp(prefix="u2sa-corpus-"))
    began = time.monotonic()
    logs = build_corpus(root / "logs")
    print(f"corpus: {len(logs)} recordings built in {time.monotonic() - began:.1f} s in {root / 'logs'}", flush=True)
    began = time.monotonic()
    hog = [sys.executable, str(REPO / "bench" / "cpu_hog.py"), *(["--workers", args.workers] if args.workers else [])]
    done = subprocess.run([*hog, "--", sys.executable, "-m",
                           "u2sa_hw.cli", "replay-check", str(root / "logs"), "--edge", args.edge], cwd=REPO)
    print(f"replay-check under cpu_hog: exit {done.returncode} in {time.monotonic() - began:.1f} s")
    return done.returncode


if __name__ == "__main__":
    sys.exit(main())
