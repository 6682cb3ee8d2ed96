"""An HSM paused longer than every heartbeat timeout restarts nothing when it wakes (issue 10, point 5).

Real `u2sa run`, real service processes, real LCM multicast. The pause and the wait after it
are measured on the processes' own stamps (a condition, never a sleep).
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path
from typing import Any

from conftest import wait_until
from supervision_helpers import Watch, hsm_profile, launch  # noqa: F401 - launch is a fixture

from u2sa_hw.bus.client import BusClient

SERVICES = ("est_a", "est_b", "est_c", "est_d")
# Heartbeats every 0.2 s, 5 may be missed: every heartbeat timeout is 1 s.
SETTINGS = ("health_interval_s = 0.2, missed_heartbeats = 5, restart_backoff_s = 0.5, max_restarts = 2, "
            "system_health_interval_s = 0.2")
PAUSE_US = 6_000_000        # the pause issue 10 saw: six heartbeat timeouts
AFTER_US = 3_000_000        # the HSM judges this long after waking: timeout + confirm_s, twice over


def test_an_hsm_paused_for_6_s_restarts_nothing_while_the_services_keep_publishing(
        tmp_path: Path, lcm_url: str, bus: BusClient, launch: Any) -> None:
    watch = Watch(bus)
    services = "".join(f'[services.{n}]\nkind = "state_estimator"\nsettings = {{ health_interval_s = 0.2 }}\n'
                       for n in SERVICES)
    vehicle = hsm_profile(tmp_path, lcm_url, services, startup_grace_s=10.0, hsm_settings=SETTINGS)
    # The launcher's watchdog would (rightly) restart the paused HSM: here it has to wake by itself.
    lp = launch(vehicle, "--watchdog", "0")
    wait_until(lambda: all((s := watch.service_state(n)) and s.state == "ok" for n in SERVICES), timeout=60,
               message="the HSM to see every service ok")
    hsm_pid = lp.status()["hsm"]["pid"]

    paused_us = time.time_ns() // 1000
    os.kill(hsm_pid, signal.SIGSTOP)
    try:
        wait_until(lambda: all(watch.stamps.get(n, 0) >= paused_us + PAUSE_US for n in SERVICES), timeout=60,
                   message="every service to publish for 6 s more while the HSM is paused")
    finally:
        os.kill(hsm_pid, signal.SIGCONT)
    woke_us = time.time_ns() // 1000
    wait_until(lambda: (m := watch.latest()) and m.header.timestamp_us >= woke_us + AFTER_US, timeout=60,
               message="the HSM judging for 3 s after it woke")

    status = lp.status()
    assert {n: (status[n]["run_id"], status[n]["restarts"]) for n in (*SERVICES, "hsm")} \
        == {n: (1, 0) for n in (*SERVICES, "hsm")}
    latest = watch.latest()
    assert {s.name: (s.state, s.restarts) for s in latest.services} == {n: ("ok", 0) for n in SERVICES}
    assert not latest.failsafe and not watch.failsafes
    out = lp.output
    assert "the HSM itself was stalled for" in out                   # it did notice the pause...
    assert "restarting est_" not in out and "restart of est_" not in out   # ...and did no harm
