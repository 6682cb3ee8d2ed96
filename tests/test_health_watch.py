"""``u2sa health --watch`` with a real service on the bus: plain text blocks into a pipe, the table redrawn
in place on a real pty; rows carry the service's state, rates and the reason of one that is not ok."""

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

from u2sa_hw import lcmtypes as t
from u2sa_hw.cli.health_watch import CLEAR, render


def test_render_cuts_the_reason_to_the_width() -> None:
    row = {"name": "gps", "state": "failed", "status": "", "reason": "x" * 300, "restarts": 2, "rx_hz": None,
           "tx_hz": 1.25, "cpu_percent": 3.0, "dropped": 0, "heartbeat_age_s": None}
    lines = render({"failsafe": True, "summary": "1 failed", "services": [row]}, width=100, now="12:00:00")
    assert lines[0] == "12:00:00  FAILSAFE ACTIVE -- 1 failed"
    assert all(len(line) <= 100 for line in lines) and lines[2].endswith("...")
    assert re.match(r"gps\s+failed\s+2\s+-\s+1\.2\s+3\.0\s+0\s+x+", lines[2])


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
