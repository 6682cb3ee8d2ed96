"""The safety chain really runs SCHED_FIFO under the launcher, and a spinning one does not hang the board.

Real system calls: skipped where real-time priority is not permitted (no root, CAP_SYS_NICE
or RLIMIT_RTPRIO). Kernel RT throttling is read, never written.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
from conftest import wait_until
from test_realtime import _profile

from u2sa_hw.launcher import Launcher, RestartPolicy
from u2sa_hw.realtime import THROTTLE_FILE, plan
from u2sa_hw.profile.loader import load_profile

PERMITTED = plan()
pytestmark = pytest.mark.skipif(PERMITTED.ceiling < 30, reason=f"real-time not permitted: {PERMITTED.notice}")

READY = ("import os, socket\n"
         "a = os.environ['NOTIFY_SOCKET']\n"
         "s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)\n"
         "s.sendto(b'READY=1', '\\0' + a[1:] if a.startswith('@') else a)\n")
SHOW = READY + ("import threading, time\n"
                "seen = {}\n"
                "t = threading.Thread(target=lambda: seen.update(thread=os.sched_getscheduler(0)))\n"
                "t.start(); t.join()\n"
                "print('policy', os.sched_getscheduler(0), os.sched_getparam(0).sched_priority, seen['thread'],"
                " flush=True)\n"
                "time.sleep(120)\n")
SPIN = READY + "while True:\n    pass\n"


def test_the_rc_mux_and_its_threads_run_fifo_and_a_sensor_driver_normal(tmp_path: Path) -> None:
    profile = load_profile(_profile(tmp_path, {"rc": "rc_mux", "gps": "gps_nmea"}))
    lines: list[tuple[str, str]] = []
    launcher = Launcher(profile, control=False, realtime=PERMITTED, output=lambda n, line: lines.append((n, line)),
                        command=lambda spec: [sys.executable, "-c", SHOW])
    launcher.start()
    try:
        wait_until(lambda: {n for n, line in list(lines) if line.startswith("policy")} == {"rc", "gps"}, timeout=30,
                   message="both children to say their policy")
    finally:
        launcher.stop(timeout=20)
    said = {n: line for n, line in lines if line.startswith("policy")}
    assert said == {"rc": f"policy {os.SCHED_FIFO} 30 {os.SCHED_FIFO}",
                    "gps": f"policy {os.SCHED_OTHER} 0 {os.SCHED_OTHER}"}
    assert ("launcher", "real-time (SCHED_FIFO): rc 30") in lines


def test_a_spinning_real_time_child_on_the_launchers_only_cpu_is_still_killed_by_the_watchdog(tmp_path: Path) -> None:
    # The worst case: one CPU for both. The launcher runs at normal priority and gets the 5 % that kernel RT
    # throttling keeps for normal tasks (50 ms of each second), enough to see the silence and send the signal.
    throttle = int(THROTTLE_FILE.read_text())
    if throttle < 0:
        pytest.skip("kernel RT throttling is off here: a real-time spinner would own the CPU")
    profile = load_profile(_profile(tmp_path, {"wheels": "odrive_can"}))
    lines: list[tuple[str, str]] = []
    launcher = Launcher(profile, control=False, realtime=PERMITTED, watchdog_s=0.5, grace_s=1.0,
                        policy=RestartPolicy(give_up_after=1), output=lambda n, line: lines.append((n, line)),
                        command=lambda spec: [sys.executable, "-c", SPIN])
    affinity = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {min(affinity)})   # the launcher's thread and its child inherit this one CPU
    try:
        launcher.start()
    finally:
        os.sched_setaffinity(0, affinity)
    try:
        assert launcher.wait(60), "the launcher never ended the spinning child"
    finally:
        launcher.stop(timeout=20)
    (status,) = launcher.status()
    assert status.watchdog_kills == 1 and status.result == "watchdog", status
    assert int(THROTTLE_FILE.read_text()) == throttle   # untouched


def _policies() -> set[tuple[int, int]]:
    found = set()
    for stat in Path("/proc/self/task").glob("*/stat"):
        fields = stat.read_text().rpartition(")")[2].split()
        found.add((int(fields[41 - 3]), int(fields[40 - 3])))
    return found


def test_the_sim_process_raises_all_its_threads_and_stop_puts_them_back() -> None:
    import threading

    release = threading.Event()
    waiter = threading.Thread(target=release.wait)   # a thread that existed before the raise
    waiter.start()
    raised = PERMITTED.raise_process()
    try:
        late: dict[str, int] = {}
        later = threading.Thread(target=lambda: late.update(policy=os.sched_getscheduler(0)))
        later.start()
        later.join()
        assert _policies() == {(os.SCHED_FIFO, 10)} and late == {"policy": os.SCHED_FIFO}
    finally:
        raised.restore()
        release.set()
        waiter.join()
    assert _policies() == {(os.SCHED_OTHER, 0)}
