#!/usr/bin/env python3
"""The recorder's memory under a flood: what a 10x burst costs in RSS, and whether it stays.

This process is the recorder (a Transport and the recorder's ``BusCapture`` writing MCAP
with the service's defaults: ``queue_size`` 20,000, 1 MiB chunks, a flush every second); a
publisher process (this script with ``--publisher``) sends the example ground vehicle's
channel mix (the one ``bench/replay.py`` measures the recorder's throughput with) at
``--factor`` (default 10) times its rates for ``--seconds`` per flood. After a warm-up at
1x (the first use of every path: zstd, finishing a chunk), it runs ``--floods`` plain
floods (default 3), then one during whose first ``--stall`` seconds the writer thread is
held (a disk that stops answering: the queue fills to its 20,000 and drops), then one more
plain flood. After each, once the queue is empty, it prints RSS (``/proc/self/status``)
against the warm-up, the live Python allocations (``sys.getallocatedblocks``) against the
warm-up, the deepest queue and the peak RSS; then the same once the file is finished and
once more after ``malloc_trim(0)`` (glibc hands free heap back); and what a full queue and a
chunk in progress can hold, to set the figures against.

Live blocks back at the warm-up's count while RSS stays higher means memory freed but kept
by the allocators (pymalloc keeps an arena while any object in it lives; glibc keeps its
heap), reused by the next flood: a plateau, not a leak.

Usage: ``python bench/recorder.py [--factor 10] [--seconds 10] [--floods 3] [--stall 3]``.
Not a test: the figures depend on the machine.
"""

from __future__ import annotations

import argparse
import ctypes
import ctypes.util
import gc
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from u2sa_hw.bus.run_keys import use_run_key  # noqa: E402
from u2sa_hw.recording.mcap_log import McapLogWriter, RunInfo  # noqa: E402
from u2sa_hw.services.recorder.capture import BusCapture  # noqa: E402
from u2sa_hw.bus.transport import Transport  # noqa: E402
from u2sa_hw.bus.udp_ports import private_lcm_url  # noqa: E402
from example_mix import EXAMPLE_RATES  # noqa: E402  (bench/ is the script's directory)

QUEUE_SIZE = 20000        # the recorder service's default queue_size
CHUNK_SIZE = 1 << 20      # McapLogWriter's default chunk size (uncompressed)


def status_kb(field: str) -> int:
    """A ``kB`` figure of this process from /proc/self/status (VmRSS, VmHWM)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


def mb(kb: int) -> str:
    """*kb* as MB with one decimal."""
    return f"{kb / 1024:.1f} MB"


def malloc_trim() -> bool:
    """Ask glibc to give freed heap back to the system; False where there is no glibc."""
    name = ctypes.util.find_library("c")
    try:
        return bool(ctypes.CDLL(name).malloc_trim(0)) if name else False
    except (OSError, AttributeError):
        return False


def publisher(url: str, factor: float, seconds: float) -> None:
    """Child process: publish the mix at *factor* times its rates for *seconds*; print the count sent."""
    tx = Transport(url, name="bench-publisher")   # signed, as every u2sa publisher is
    plan = [(ch, rate * factor, bytes(size)) for ch, (rate, size) in EXAMPLE_RATES.items()]
    credit = {ch: 0.0 for ch, _, _ in plan}
    sent, start = 0, time.monotonic()
    while (now := time.monotonic()) - start < seconds:
        for ch, rate, payload in plan:
            while rate * (now - start) - credit[ch] >= 1.0:
                tx.publish_bytes(ch, payload)
                credit[ch] += 1.0
                sent += 1
        time.sleep(max(0.0, 0.002 - (time.monotonic() - now)))
    print(sent, flush=True)


class StallableDisk:
    """The capture's ``disk_usage`` hook: plenty of space; while :attr:`stalled` is set, the writer
    thread is held in it (as by a disk that stopped answering), so the queue fills."""

    def __init__(self) -> None:
        self.stalled = threading.Event()
        self.release = threading.Event()

    def __call__(self, path: Path) -> Any:
        if self.stalled.is_set():
            self.release.wait(60)
        return shutil.disk_usage(path)


def flood(url: str, factor: float, seconds: float, capture: BusCapture, *, disk: StallableDisk,
          stall_s: float = 0.0) -> tuple[int, int]:
    """One burst from a publisher process (the writer held for its first *stall_s*); (messages sent,
    deepest queue seen) once the queue is empty."""
    deepest = 0
    done = threading.Event()

    def watch() -> None:
        nonlocal deepest
        began = time.monotonic()
        while not done.wait(0.02):
            deepest = max(deepest, capture.queue_depth)
            if disk.stalled.is_set() and time.monotonic() - began >= stall_s:
                disk.stalled.clear()
                disk.release.set()

    if stall_s:
        disk.release.clear()
        disk.stalled.set()
    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    child = subprocess.run([sys.executable, __file__, "--publisher", url, str(factor), str(seconds)],
                           capture_output=True, text=True, timeout=seconds + 120)
    deadline = time.monotonic() + 30
    while (capture.queue_depth or disk.stalled.is_set()) and time.monotonic() < deadline:
        time.sleep(0.05)
    done.set()
    watcher.join()
    return int(child.stdout.strip() or 0), deepest


def stage(name: str, base: int, blocks: int, note: str = "") -> None:
    """One line: RSS and its growth, live Python allocations (pymalloc blocks) against the start."""
    gc.collect()
    rss = status_kb("VmRSS")
    print(f"  {name:32} RSS {mb(rss):>8} ({'+' if rss >= base else ''}{mb(rss - base)}), live Python blocks "
          f"{sys.getallocatedblocks() - blocks:+d}" + (f"; {note}" if note else ""))


def main() -> int:
    """Run the floods and print the figures."""
    if len(sys.argv) == 5 and sys.argv[1] == "--publisher":
        publisher(sys.argv[2], float(sys.argv[3]), float(sys.argv[4]))
        return 0
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--factor", type=float, default=10.0, help="times the example vehicle's rates (default 10)")
    p.add_argument("--seconds", type=float, default=10.0, help="length of each flood (default 10)")
    p.add_argument("--floods", type=int, default=3, help="plain floods before the held one (default 3)")
    p.add_argument("--stall", type=float, default=3.0, metavar="S",
                   help="then a flood holding the writer for S s, so the queue fills, and one more plain flood "
                   "(default 3; 0: neither)")
    args = p.parse_args()
    use_run_key()

    url = private_lcm_url(options="ttl=0&recv_buf_size=4194304")
    work = Path(tempfile.mkdtemp(prefix="u2sa-bench-recorder-rss-"))
    transport = Transport(url, name="bench-recorder")
    writer = McapLogWriter(work, path=work / "flood.mcap", chunk_size=CHUNK_SIZE, run=RunInfo(vehicle="bench"))
    disk = StallableDisk()
    capture = BusCapture(transport, writer, queue_size=QUEUE_SIZE, min_free_mb=50, disk_usage=disk)
    capture.start()
    transport.start()
    nominal = sum(rate for rate, _ in EXAMPLE_RATES.values())
    mean_payload = sum(rate * size for rate, size in EXAMPLE_RATES.values()) / nominal
    print(f"recorder RSS: the example vehicle's mix ({nominal:.0f} msg/s on {len(EXAMPLE_RATES)} channels, mean "
          f"payload {mean_payload:.0f} B) x {args.factor:g} for {args.seconds:g} s per flood; queue_size "
          f"{QUEUE_SIZE}, chunks of {CHUNK_SIZE >> 20} MiB")
    flood(url, 1.0, 3.0, capture, disk=disk)   # first use of every path (zstd, chunk finishing) at 1x
    gc.collect()
    base, blocks = status_kb("VmRSS"), sys.getallocatedblocks()
    stage("after a 3 s warm-up at 1x", base, blocks)
    floods = [(f"flood {n}", 0.0) for n in range(1, args.floods + 1)]
    if args.stall:
        floods += [(f"flood {args.floods + 1} (writer held {args.stall:g} s)", args.stall),
                   (f"flood {args.floods + 2}", 0.0)]
    for name, stall in floods:
        dropped = capture.stats.dropped
        sent, deepest = flood(url, args.factor, args.seconds, capture, disk=disk, stall_s=stall)
        stage(f"after {name}", base, blocks, f"{sent} sent, deepest queue {deepest}, "
              f"{capture.stats.dropped - dropped} dropped; peak RSS so far {mb(status_kb('VmHWM'))}")
        time.sleep(2.0)
    capture.stop()
    transport.stop()
    stage("file finished", base, blocks)
    trimmed = malloc_trim()
    stage("after malloc_trim(0)" if trimmed else "(no malloc_trim here)", base, blocks)
    s = capture.stats
    print(f"  {s.written} written, {s.dropped} dropped, {s.received - s.written - s.dropped} unaccounted")
    item = 72 + 8 + 32 + 60 + 33 + mean_payload   # tuple, deque slot, int, channel str, bytes header, payload
    print(f"  bounds: a full queue holds about {QUEUE_SIZE} x {item:.0f} B = {QUEUE_SIZE * item / 1e6:.1f} MB; a chunk "
          f"in progress {CHUNK_SIZE / 1e6:.1f} MB uncompressed, 2-3 copies of it while it is finished, and a "
          f"(time, offset) tuple per message (~125 B: {CHUNK_SIZE / (mean_payload + 31) * 125 / 1e6:.1f} MB "
          "for a full chunk)")
    shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
