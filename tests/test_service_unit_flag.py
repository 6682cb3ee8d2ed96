"""`u2sa service --unit` (what the installed units run): the profile alone decides bus security.

A service started with ``--unit`` and ``U2SA_BUS_SECURITY=open`` in its environment still signs
and verifies: a signed client discovers it, its health says signed, an unsigned STOP from a
process without the key is refused and counted, and its log names the ignored variable once.
Without ``--unit`` the variable still opens the bus (benches and tests rely on it), and
``u2sa check`` warns where the variable is set.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

from conftest import U2SA, ServiceProcesses, wait_until

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.bus.key import KEY_ENV

SERVICE = "state_estimator"
IGNORED = "$U2SA_BUS_SECURITY='open' ignored: an installed unit (--unit) follows the vehicle profile alone"

UNSIGNED_STOP = """\
import sys
from u2sa_hw import channels as ch, lcmtypes as t
from u2sa_hw.bus.transport import Transport

tx = Transport(sys.argv[1], name="laptop")   # U2SA_BUS_SECURITY=open and no key: unsigned
stop = t.StopCommand(); stop.all = True
assert tx.publish(ch.STOP, stop)
"""


class Details:
    """The latest health details of each service, from a signed client of the test's own."""

    def __init__(self, bus: BusClient) -> None:
        self.latest: dict[str, dict[str, str]] = {}
        self._lock = threading.Lock()
        bus.transport.subscribe(ch.HEALTH, t.Health, self._on_health)

    def _on_health(self, _c: str, msg: t.Health) -> None:
        with self._lock:
            self.latest[msg.name] = {kv.key: kv.value for kv in msg.details}

    def of(self, name: str) -> dict[str, str]:
        with self._lock:
            return dict(self.latest.get(name, {}))


def service_log(services: ServiceProcesses, name: str) -> str:
    path = services.workdir / ".u2sa" / "logs" / f"{name}.log"
    return path.read_text() if path.exists() else ""


def test_a_unit_ignores_bus_security_open_from_its_environment(services: ServiceProcesses, bus: BusClient) -> None:
    details = Details(bus)
    proc = services.start(SERVICE, "--unit", U2SA_BUS_SECURITY="open")
    # A signed client hears it at all: an open service's answers would be dropped as unsigned.
    found = wait_until(lambda: bus.discover(timeout=0.5, name=SERVICE), timeout=30, message=f"{SERVICE} to answer")
    assert found[0].pid == proc.pid
    wait_until(lambda: details.of(SERVICE).get("bus_security", "").startswith("signed"), timeout=15,
               message="health saying the bus is signed")
    keyless = {k: v for k, v in os.environ.items() if k != KEY_ENV}
    subprocess.run([sys.executable, "-c", UNSIGNED_STOP, services.url],
                   env={**keyless, "U2SA_BUS_SECURITY": "open"}, check=True, timeout=60)
    wait_until(lambda: "U2SA_STOP: unsigned 1" in details.of(SERVICE).get("bus_rejected", ""), timeout=15,
               message="the unsigned stop counted as rejected")
    assert proc.poll() is None, "the unsigned stop stopped a --unit service"
    log = service_log(services, SERVICE)
    assert log.count(IGNORED) == 1, log
    assert " WARN " in next(line for line in log.splitlines() if IGNORED in line)   # the warning level
    assert "the bus is open" not in log


def test_without_unit_the_variable_still_opens_the_bus(services: ServiceProcesses) -> None:
    proc = services.start(SERVICE, U2SA_BUS_SECURITY="open")
    wait_until(lambda: "the bus is open" in service_log(services, SERVICE), timeout=30,
               message="the service's warning that the bus is open")
    assert proc.poll() is None
    assert IGNORED.split(":")[0] not in service_log(services, SERVICE)


def test_check_warns_that_installed_units_ignore_the_variable(tmp_path: Path) -> None:
    profile = tmp_path / "vehicle.toml"
    profile.write_text('[vehicle]\nname = "bench"\n\n[services.estimator]\nkind = "state_estimator"\n')
    clean = {k: v for k, v in os.environ.items() if k != "U2SA_BUS_SECURITY"}
    quiet = subprocess.run([*U2SA, "check", "--vehicle", str(profile)], env=clean, capture_output=True, text=True,
                           timeout=60)
    assert quiet.returncode == 0, quiet.stdout + quiet.stderr
    assert "U2SA_BUS_SECURITY" not in quiet.stdout
    told = subprocess.run([*U2SA, "check", "--vehicle", str(profile)], env={**clean, "U2SA_BUS_SECURITY": "open"},
                          capture_output=True, text=True, timeout=60)
    assert told.returncode == 0, told.stdout + told.stderr   # a warning, not an error
    line = next(line for line in told.stdout.splitlines() if "U2SA_BUS_SECURITY" in line)
    assert line.startswith(f"warning: {profile} [vehicle.bus_security]: $U2SA_BUS_SECURITY='open' is set"), line
    assert "installed units (u2sa service --unit) ignore it" in line
    assert "u2sa run, the benches and the tests still honour" in line
    assert "0 error(s), 1 warning(s)" in told.stdout
    # A profile that says: the units follow it, and so does u2sa run.
    profile.write_text('[vehicle]\nname = "bench"\nbus_security = "signed"\n\n'
                       '[services.estimator]\nkind = "state_estimator"\n')
    said = subprocess.run([*U2SA, "check", "--vehicle", str(profile)], env={**clean, "U2SA_BUS_SECURITY": "open"},
                          capture_output=True, text=True, timeout=60)
    assert 'follow the profile\'s bus_security = "signed"' in said.stdout, said.stdout
