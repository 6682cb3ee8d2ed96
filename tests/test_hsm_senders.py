"""The HSM counts a restart only when a service's own signed sender is replaced (issue 11).

Real processes over real multicast: ``u2sa run`` starts an estimator and the HSM; another
process holding the same key (another stack's service of the same name, as a second
simulation given the vehicle's key would be) sends Health as that estimator from its own
pid. The HSM shows it and counts no restart. Then the real estimator is killed: the
launcher starts it again and the HSM counts exactly that one restart. Last, the other
stack's stop and one without the key are dropped, and ``u2sa health`` shows both.
The rules themselves, with a clock of the test's own: a faster impostor never takes over.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

from conftest import wait_until
from supervision_helpers import Watch, hsm_profile, launch  # noqa: F401 - launch is a fixture

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.launcher.children import u2sa_command
from u2sa_hw.services.hsm.senders import ServiceSenders
from u2sa_hw.bus.transport import Transport

OTHER_STACK = """\
import os, sys, time
from u2sa_hw import channels as ch, lcmtypes as t
from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.launcher.children import u2sa_command
from u2sa_hw.services.hsm.senders import ServiceSenders
from u2sa_hw.bus.transport import Transport

bus = BusClient(sys.argv[1], name="est_a", system_id=1)   # the session's key, the vehicle's system id
end = time.monotonic() + float(sys.argv[2])
while time.monotonic() < end:
    h = t.Health()
    h.name, h.service_type, h.status, h.pid, h.host = "est_a", "state_estimator", "ok", os.getpid(), "other-stack"
    bus.publish(ch.HEALTH, h)
    time.sleep(0.1)
bus.close()
"""


def test_health_from_another_process_of_the_name_is_no_restart_and_a_real_one_is(
        tmp_path: Path, lcm_url: str, bus: BusClient, launch: Any) -> None:
    watch = Watch(bus)
    vehicle = hsm_profile(tmp_path, lcm_url, '[services.est_a]\nkind = "state_estimator"\n'
                      "settings = { health_interval_s = 0.2 }\n", startup_grace_s=10.0)
    launch(vehicle, "--grace", "3", "--watchdog", "0")
    wait_until(lambda: (s := watch.service_state("est_a")) and s.state == "ok", timeout=60,
               message="the HSM to see est_a ok")
    real_pid = watch.pids["est_a"][-1]

    other = subprocess.Popen([sys.executable, "-c", OTHER_STACK, lcm_url, "4"])
    try:
        shown = wait_until(lambda: (s := watch.service_state("est_a")) and "another process also sends Health"
                           in s.last_error and s, timeout=60, message="the HSM to show the other est_a")
        assert "other-stack" in shown.last_error and shown.restarts == 0
        assert other.wait(timeout=60) == 0
    finally:
        if other.poll() is None:
            other.kill()
    assert any(pid != real_pid for pid in watch.pids["est_a"]), "the other process's Health never arrived"
    states = [s for m in list(watch.system) for s in m.services if s.name == "est_a"]
    assert states and all(s.restarts == 0 for s in states), [s.restarts for s in states]

    os.kill(real_pid, signal.SIGKILL)    # a real crash: the launcher starts it again
    wait_until(lambda: (s := watch.service_state("est_a")) and s.restarts >= 1 and s.state == "ok", timeout=60,
               message="the HSM to count the real restart")
    wait_until(lambda: "another process" not in watch.service_state("est_a").last_error, timeout=60,
               message="the other process's note to go once it is silent")
    assert watch.service_state("est_a").restarts == 1

    # The other stack's stop (the key, another system id) and a stop without the key: u2sa health shows both.
    other_vehicle = BusClient(lcm_url, name="vehicle-2", system_id=2)
    stop = t.StopCommand()
    stop.all = True
    other_vehicle.publish(ch.STOP, stop)
    other_vehicle.close()
    Transport(lcm_url, name="laptop", security="open").publish(ch.STOP, stop)

    def shown_by_health() -> dict[str, Any] | None:
        r = subprocess.run([*u2sa_command(), "health", "--vehicle", str(vehicle), "--json"], capture_output=True,
                           text=True, timeout=60)
        rows = {s["name"]: s for s in json.loads(r.stdout)["services"]} if r.returncode == 0 else {}
        est = rows.get("est_a")
        return est if est and est["foreign"] >= 1 and est["bad_signature"] >= 1 else None

    est = wait_until(shown_by_health, timeout=60, message="u2sa health to show est_a's foreign and unsigned stop")
    assert "U2SA_STOP: unsigned 1, foreign 1" in est["rejected_by_channel"] and est["state"] == "ok"
    table = subprocess.run([*u2sa_command(), "health", "--vehicle", str(vehicle)], capture_output=True, text=True,
                           timeout=60)
    assert "BAD SIG" in table.stdout and "FOREIGN" in table.stdout


class _Health:
    name, host = "gps", "rover"

    def __init__(self, pid: int) -> None:
        self.pid = pid


def test_a_sender_beside_the_live_one_never_takes_over_and_a_restart_does() -> None:
    senders, timeout = ServiceSenders(), 3.0
    assert senders.admit("a", _Health(1), 0.0, timeout) and senders.admit("a", _Health(1), 1.0, timeout)
    # "b" talks four times as often as "a", between a's beats: never adopted.
    for k in range(40):
        now = 2.0 + k * 0.25
        if k % 4 == 0:
            assert senders.admit("a", _Health(1), now, timeout)
        else:
            assert not senders.admit("b", _Health(2), now, timeout)
    assert "pid 2 on rover" in senders.note(11.9, timeout) and senders.note(20.0, timeout) == ""
    # "a" dies; its replacement "c" is adopted once a has been silent since c's previous beat.
    assert not senders.admit("c", _Health(3), 12.0, timeout)
    assert senders.admit("c", _Health(3), 13.0, timeout) and senders.sender == "c"
    assert not senders.admit("a", _Health(1), 13.5, timeout)
    assert senders.admit("c", _Health(3), 14.0, timeout)   # a replaced sender speaking again was not dead
