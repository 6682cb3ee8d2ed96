"""What the pilot's Ed25519 signatures cost the lean stack (issue 23): CPU per message and memory per process.

RC_MODE (20 Hz) and MANUAL_CMD (25 Hz, in manual) are signed by the RC mux with the pilot's
private key and checked by every receiver with the public key (u2sa_hw.bus.pilot). This prints,
on this machine:

- the hot, in-process time of one HMAC sign/verify (every other channel) against one Ed25519
  sign/verify (medians of many);
- the CPU that adds per receiver at the pilot's rates, and for the example ground vehicle's
  receivers (its actuators, control and recorder) and its RC mux, in % of one core;
- what importing PyNaCl's Ed25519 adds to a process (RSS and PSS from /proc), measured in a
  fresh interpreter, as each receiver pays it once.

    python bench/pilot_cost.py [--samples N]

A Pi 4 core runs this several times slower: multiply the % by the ratio bench/sbc.py reports.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from u2sa_hw import channels as ch  # noqa: E402
from u2sa_hw import lcmtypes as t  # noqa: E402
from u2sa_hw.bus.auth import BusAuth, Keyring  # noqa: E402
from u2sa_hw.bus.run_keys import fresh_key_file  # noqa: E402

RC_MODE_HZ, MANUAL_HZ = 20.0, 25.0
# The example ground vehicle's receivers of the pilot's channels: (name, hears MANUAL_CMD too)
GROUND_RECEIVERS = (("wheels", True), ("pan", True), ("control", False), ("recorder", True))

MEMORY_PROBE = """\
import sys
def sizes():
    rss = pss = 0
    for line in open('/proc/self/smaps_rollup'):
        if line.startswith('Rss:'): rss = int(line.split()[1])
        if line.startswith('Pss:'): pss = int(line.split()[1])
    return rss, pss
before = sizes()
if sys.argv[1] == 'pilot':
    from nacl.signing import VerifyKey  # what a receiver imports
after = sizes()
print(after[0] - before[0], after[1] - before[1])
"""


def median_us(step, samples: int) -> float:
    """The median of *samples* timed calls of *step*, in µs."""
    times = []
    for _ in range(samples):
        start = time.perf_counter_ns()
        step()
        times.append(time.perf_counter_ns() - start)
    return statistics.median(times) / 1000.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--samples", type=int, default=3000, help="timed calls per step (default 3000)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="u2sa-pilot-cost-") as tmp:
        key = fresh_key_file(tmp)
        signer, receiver = BusAuth(Keyring(key)), BusAuth(Keyring(key))
        mode = t.RcMode().encode()
        sticks = t.PercentageCommand().encode()
        steps = {}
        hmac_packets = iter([signer.sign(ch.STATE_INFO, mode) for _ in range(args.samples)])
        pilot_packets = iter([signer.sign(ch.RC_MODE, mode) for _ in range(args.samples)])
        steps["HMAC sign"] = median_us(lambda: signer.sign(ch.STATE_INFO, mode), args.samples)
        steps["HMAC verify"] = median_us(lambda: receiver.verify(ch.STATE_INFO, next(hmac_packets)), args.samples)
        steps["Ed25519 sign"] = median_us(lambda: signer.sign(ch.MANUAL_CMD, sticks), args.samples)
        steps["Ed25519 verify"] = median_us(lambda: receiver.verify(ch.RC_MODE, next(pilot_packets)), args.samples)
    print("per message, hot, in-process (us, median of %d): " % args.samples
          + ", ".join(f"{name} {us:.1f}" for name, us in steps.items()))
    extra_us = steps["Ed25519 verify"] - steps["HMAC verify"]
    both = RC_MODE_HZ + MANUAL_HZ
    per_rx_manual = both * steps["Ed25519 verify"] / 1e4          # % of one core
    per_rx_extra = both * extra_us / 1e4
    print(f"one receiver of RC_MODE and MANUAL_CMD ({both:g} msg/s in manual): {per_rx_manual:.3f} % of one core "
          f"for the checks, {per_rx_extra:.3f} % more than HMAC")
    total = sum((RC_MODE_HZ + (MANUAL_HZ if manual else 0.0)) * steps["Ed25519 verify"] for _, manual in
                GROUND_RECEIVERS) / 1e4
    signing = both * steps["Ed25519 sign"] / 1e4
    print(f"example ground vehicle ({', '.join(n for n, _ in GROUND_RECEIVERS)} receive; rc signs): "
          f"{total:.3f} % of one core checking + {signing:.3f} % signing = {total + signing:.3f} %")
    for what in ("bare", "pilot"):
        out = subprocess.run([sys.executable, "-c", MEMORY_PROBE, what], capture_output=True, text=True, check=True)
        rss, pss = (int(v) for v in out.stdout.split())
        if what == "pilot":
            print(f"importing PyNaCl's Ed25519 in a receiver: +{rss / 1024:.1f} MB RSS, +{pss / 1024:.1f} MB PSS "
                  f"(this process alone; shared pages count less once several processes map them)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
