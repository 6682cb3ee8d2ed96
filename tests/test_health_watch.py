"""``u2sa health --watch`` with a real service on the bus: plain text blocks into a pipe, the table redrawn
in place on a real pty; rows carry the service's state, rates and the reason of one that is not ok; below
them the autonomy line of the one-shot ``u2sa health``, following the pilot's RC_MODE live."""

from __future__ import annotations

import os
import pty
import re
import select
import subprocess
import threading
import time
from typing import Any

import pytest
from conftest import U2SA, ServiceProcesses, wait_until

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.service.health import set_details
from u2sa_hw.cli.health_cmd import autonomy_line, autonomy_report
from u2sa_hw.cli.health_watch import CLEAR, RC_STALE_S, AutonomyView, render


def test_render_cuts_the_reason_to_the_width() -> None:
    row = {"name": "gps", "state": "failed", "status": "", "reason": "x" * 300, "restarts": 2, "rx_hz": None,
           "tx_hz": 1.25, "cpu_percent": 3.0, "dropped": 0, "heartbeat_age_s": None}
    lines = render({"failsafe": True, "summary": "1 failed", "services": [row]}, width=100, now="12:00:00")
    assert lines[0] == "12:00:00  FAILSAFE ACTIVE -- 1 failed"
    assert all(len(line) <= 100 for line in lines) and lines[2].endswith("...")
    assert re.match(r"gps\s+failed\s+2\s+-\s+1\.2\s+3\.0\s+0\s+x+", lines[2])
    no_hsm = render({"failsafe": None, "summary": "no HSM heard", "services": []}, width=100, now="12:00:00")
    assert no_hsm[0] == "12:00:00  failsafe unknown -- no HSM heard"   # without an HSM no one counts them


def rc_mode(*, mode: str, armed: bool, granted: bool, blocked_by: str = "", hold: bool = False) -> t.RcMode:
    msg = t.RcMode()
    msg.mode, msg.mode_name = {"manual": 0, "autonomous": 1, "no signal": 2}[mode], mode
    msg.armed, msg.autonomy_enabled, msg.blocked_by, msg.hold = armed, granted, blocked_by, hold
    msg.header.source = "rc"
    return msg


def mux_health(name: str = "rc", **details: object) -> t.Health:
    msg = t.Health()
    msg.name = name
    set_details(msg, details)
    return msg


def test_the_autonomy_line_is_the_one_shots_from_rc_mode_or_health_whichever_came_last() -> None:
    view = AutonomyView()
    assert view.lines(0.0) == []   # no mux heard: no line, as the one-shot prints none
    health = mux_health(mode="manual", autonomy_enabled=False, enable_blocked_by="mode manual", armed=True,
                        hold=False)
    view.on_health(health, 10.0)
    (line,) = view.lines(10.5)
    assert line == "autonomy (rc, RC manual, armed): refused: mode manual"
    assert line == autonomy_line(autonomy_report({"rc": health})[0])   # the one-shot's words
    view.on_rc_mode(rc_mode(mode="autonomous", armed=True, granted=True), 11.0)
    assert view.lines(11.2) == ["autonomy (rc, RC autonomous, armed): GRANTED"]
    view.on_rc_mode(rc_mode(mode="autonomous", armed=True, granted=True, hold=True), 11.3)
    assert "GRANTED, but HOLD: outputs neutral" in view.lines(11.4)[0]
    view.on_health(health, 11.5)   # the newer view wins, whichever channel brought it
    assert view.lines(11.6)[0].endswith("refused: mode manual")
    stale = view.lines(11.5 + RC_STALE_S + 1.0)[0]
    age = f"{RC_STALE_S + 1:.1f}"
    assert stale == f"autonomy (rc, RC manual, armed): refused: mode manual (nothing from it for {age} s)"
    view.on_health(mux_health("gps", fix="3D"), 12.0)   # a service that is no RC mux gives no line
    assert len(view.lines(12.0)) == 1
    long = "autonomy (rc, RC autonomous, armed): refused: pre-arm check failed: gps: no 3D fix"
    lines = render({"failsafe": False, "summary": "all ok", "services": []}, width=40, now="12:00:00",
                   autonomy=[long, "autonomy (b, RC manual, armed): GRANTED"])
    assert lines[-2:] == [long[:37] + "...", "autonomy (b, RC manual, armed): GRANTED"]


@pytest.mark.timeout(120)
def test_watch_follows_the_pilots_rc_mode_live(services: ServiceProcesses, bus: Any) -> None:
    """RC_MODE signed with the pilot key (this session's key directory holds it, as the RC mux's does): the watch
    prints GRANTED, then the refusal and why when the mux sends it, then that the mux went silent."""
    current = [rc_mode(mode="autonomous", armed=True, granted=True)]
    stop = threading.Event()

    def mux() -> None:
        while not stop.wait(0.05):   # the mux's 20 Hz
            assert bus.transport.publish(ch.RC_MODE, current[0])

    out: list[str] = []
    proc = subprocess.Popen([*U2SA, "health", "--watch", "--interval", "0.2"], cwd=services.workdir,
                            env=services.env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    services.procs.append(proc)
    reader = threading.Thread(target=lambda: out.extend(iter(proc.stdout.readline, "")), daemon=True)
    reader.start()
    publisher = threading.Thread(target=mux, daemon=True)
    publisher.start()

    def last_autonomy() -> str:
        assert proc.poll() is None, proc.stderr.read()
        lines = [x.strip() for x in list(out) if x.startswith("autonomy (")]
        return lines[-1] if lines else ""

    try:
        wait_until(lambda: last_autonomy() == "autonomy (rc, RC autonomous, armed): GRANTED", timeout=30,
                   message=f"the watch to say autonomy is granted (last lines {out[-4:]})")
        why = "pre-arm check failed: gps: no 3D fix (fix type 2D, 7 satellites)"
        current[0] = rc_mode(mode="autonomous", armed=True, granted=False, blocked_by=why)
        wait_until(lambda: last_autonomy() == f"autonomy (rc, RC autonomous, armed): refused: {why}", timeout=30,
                   message=f"the watch to say why autonomy is refused (last lines {out[-4:]})")
        current[0] = rc_mode(mode="manual", armed=True, granted=False, blocked_by="mode manual")
        wait_until(lambda: last_autonomy() == "autonomy (rc, RC manual, armed): refused: mode manual", timeout=30,
                   message=f"the watch to follow the switch to manual (last lines {out[-4:]})")
        stop.set()
        publisher.join()
        wait_until(lambda: "refused: mode manual (nothing from it for" in last_autonomy(), timeout=30,
                   message=f"the watch to say the mux went silent (last lines {out[-4:]})")
    finally:
        stop.set()
        proc.terminate()
    assert proc.wait(timeout=30) == 0
    reader.join(timeout=30)
    assert "\x1b" not in "".join(out)


@pytest.mark.timeout(120)
def test_watch_lists_services_with_rates_into_a_pipe_and_redraws_on_a_tty(services: ServiceProcesses,
                                                                           bus: Any) -> None:
    services.start("world", "--kind", "world_modeler")
    wait_until(lambda: any(r.name == "world" for r in bus.discover(timeout=0.3)), timeout=30,
               message="the world modeler")
    # An HSM's view, published by the test: a service it calls failed, with its reason.
    sysh = t.SystemHealth()
    gone = t.ServiceState()
    gone.name, gone.state, gone.restarts, gone.last_error = "gps", "failed", 3, "/dev/u2sa/gps: no such device"
    world = t.ServiceState()
    world.name, world.state = "world", "ok"
    sysh.services, sysh.num_services, sysh.summary = [world, gone], 2, "1 failed"
    stop_hsm = [False]

    def hsm() -> None:
        while not stop_hsm[0]:
            bus.publish("U2SA_SYSTEM_HEALTH", sysh)
            time.sleep(0.2)

    thread = threading.Thread(target=hsm, daemon=True)
    thread.start()
    try:
        done = services.cli("health", "--watch", "--interval", "0.5", "--count", "6", timeout=60)
        assert done.returncode == 0, done.stderr
        assert "\x1b" not in done.stdout
        last = done.stdout.strip().split("\n\n")[-1].splitlines()
        assert last[0].endswith("failsafe off -- 1 failed") and last[1].startswith("SERVICE")
        rows = {line.split()[0]: line for line in last[2:]}
        assert re.match(r"world\s+ok\s+ok\s+0\s+\d+\.\d\s+\d+\.\d", rows["world"]), rows
        assert float(rows["world"].split()[5]) > 0   # it publishes WORLD_SUMMARY and health: tx rate above 0
        assert re.match(r"gps\s+failed\s+3\s+-\s+-\s+-\s+-\s+/dev/u2sa/gps: no such device", rows["gps"]), rows

        master, slave = pty.openpty()
        proc = subprocess.Popen([*U2SA, "health", "--watch", "--interval", "0.3", "--count", "3"],
                                cwd=services.workdir, env=services.env(), stdin=slave, stdout=slave,
                                stderr=subprocess.PIPE)
        os.close(slave)
        screen = b""
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            ready, _, _ = select.select([master], [], [], 0.5)
            if ready:
                try:
                    chunk = os.read(master, 65536)
                except OSError:   # the pty closed: the command ended
                    break
                if not chunk:
                    break
                screen += chunk
            elif proc.poll() is not None:
                break
        assert proc.wait(timeout=30) == 0, proc.stderr.read()
        os.close(master)
        text = screen.decode()
        assert text.count(CLEAR) == 3 and "world" in text.split(CLEAR)[-1]
    finally:
        stop_hsm[0] = True
        thread.join()
