"""GPIO drivers: outputs as an Actuator and inputs (e-stop, bumpers) as a Sensor, each as a real
service process against the mock GPIO chip in this process; debounce and config parsing on their own."""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any, Iterator

import pytest
from conftest import ServiceProcesses, wait_until
from gpio_driver_harness import BusCollector
from serial_driver_harness import start_driver, write_profile

from u2sa_hw.drivers.gpio.driver import DebouncedInput
from u2sa_hw.drivers.gpio.lines import parse_levels, parse_line_map, parse_names, parse_positions
from u2sa_hw.mocks.gpio_chip import MockGpioChip
from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.config.fields import ConfigError
from u2sa_hw.ports.tap import raw_channel

MS = 1_000_000
LAMP, BRAKE = 17, 18
ESTOP, BUMP, DOOR = 4, 22, 23


# ---------------------------------------------------------------- pure parts -------------------
def test_line_maps_and_lists_parse_and_bad_ones_name_the_field() -> None:
    assert parse_line_map(" lamp=17, brake = 18 ,", service="io", key="outputs") == {"lamp": 17, "brake": 18}
    assert parse_names("estop, bump", known=["estop", "bump"], service="io", key="failsafe_on") == ["estop", "bump"]
    assert parse_levels("brake=1", known=["brake"], service="io", key="safe_levels") == {"brake": 1}
    assert parse_positions("bump=0.45:-0.1:0.2", known=["bump"], service="io", key="positions") == {
        "bump": (0.45, -0.1, 0.2)}
    bad = [(parse_line_map, "lamp", {}), (parse_line_map, "lamp=x", {}), (parse_line_map, "a=1,b=1", {}),
           (parse_line_map, "a=1,a=2", {}), (parse_names, "nope", {"known": ["a"]}),
           (parse_levels, "a=2", {"known": ["a"]}), (parse_levels, "b=1", {"known": ["a"]}),
           (parse_positions, "a=1:2", {"known": ["a"]})]
    for fn, text, extra in bad:
        with pytest.raises(ConfigError, match="service 'io': config 'k'"):
            fn(text, service="io", key="k", **extra)


def test_debounce_needs_the_level_to_hold() -> None:
    line = DebouncedInput(level=0, debounce_ns=10 * MS, at_ns=0)
    line.edge(True, 100 * MS)
    line.edge(False, 101 * MS)          # a bounce back within the window
    assert not line.settle(200 * MS) and line.level == 0
    line.edge(True, 300 * MS)
    assert not line.settle(309 * MS)
    assert line.settle(310 * MS) and line.level == 1
    assert not line.settle(400 * MS)    # no change, no event
    instant = DebouncedInput(level=1, debounce_ns=0, at_ns=0)
    instant.edge(False, 5)
    assert instant.settle(5) and instant.level == 0


# ---------------------------------------------------------------- processes --------------------
@pytest.fixture
def chip() -> Iterator[MockGpioChip]:
    path = Path(tempfile.mkdtemp(prefix="u2sa-gpio-", dir="/tmp"))  # short: Unix socket paths are limited
    # release_level None: released outputs keep their level, so a safe level after a stop is the driver's doing
    c = MockGpioChip(socket_path=str(path / "gpio.sock"), release_level=None).start()
    yield c
    c.stop()
    shutil.rmtree(path, ignore_errors=True)


def start(services: ServiceProcesses, tmp_path: Path, *, name: str, kind: str, settings: dict[str, Any],
          socket: str) -> subprocess.Popen:
    """The service *name*, its device (named after it) the mock chip served at *socket*."""
    profile = write_profile(tmp_path, name=name, kind=kind, settings=settings,
                            devices={name: f"mock+gpio://{socket}"})
    return start_driver(services, profile, name)


def command(bus: BusClient, actuator: str, percent: float) -> None:
    cmd = t.PercentageCommand()
    cmd.base.actuator_name, cmd.percentage = actuator, percent
    bus.publish(ch.ACTUATOR_CMD, cmd)


def failsafe(bus: BusClient, active: bool) -> None:
    msg = t.Failsafe()
    msg.active, msg.reason = active, "test"
    bus.publish(ch.FAILSAFE, msg)


def output_changes(chip: MockGpioChip, since: int) -> list[tuple[int, int]]:
    return [(r.line, r.value) for r in list(chip.history)[since:] if r.kind == "output"]


def test_outputs_switch_at_50_percent_and_go_to_safe_levels(chip: MockGpioChip, tmp_path: Path,
                                                            services: ServiceProcesses, bus: BusClient) -> None:
    col = BusCollector(bus).listen(ch.HEALTH, t.Health).listen(raw_channel("io"), None)
    proc = start(services, tmp_path, name="io", kind="gpio_output",
                 socket=chip.socket_path, settings={"outputs": "lamp=17,brake=18", "safe_levels": "brake=1",
                           "command_timeout_s": 0.5, "rc_gating": False, "record_raw": True})
    wait_until(lambda: chip.consumers().get(LAMP) == "u2sa:io", message="the lines requested", timeout=30)
    assert (chip.read_output(LAMP), chip.read_output(BRAKE)) == (0, 1), "started at the safe levels"

    steps = [("lamp", 100.0, (LAMP, 1)), ("lamp", 49.9, (LAMP, 0)), ("lamp", 50.0, (LAMP, 1)),
             ("brake", -100.0, (BRAKE, 0))]
    for actuator, percent, change in steps:
        mark = len(chip.history)
        command(bus, actuator, percent)
        wait_until(lambda: change in output_changes(chip, mark), message=f"{actuator} {percent} % -> {change}")

    mark = len(chip.history)
    failsafe(bus, True)
    wait_until(lambda: {(LAMP, 0), (BRAKE, 1)} <= set(output_changes(chip, mark)), message="safe levels on FAILSAFE")
    command(bus, "lamp", 100.0)
    details = col.health_of("io", lambda d: d["ignored"] == "1", message="the command ignored during the failsafe")
    assert (details["lamp"], details["brake"], chip.read_output(LAMP)) == ("0", "1", 0)
    failsafe(bus, False)
    col.health_of("io", lambda d: d["failsafe"] == "False", since=col.count(ch.HEALTH), message="failsafe cleared")

    mark = len(chip.history)
    command(bus, "lamp", 100.0)
    command(bus, "not-ours", 100.0)
    wait_until(lambda: output_changes(chip, mark)[:2] == [(LAMP, 1), (LAMP, 0)],
               message="lamp on, then off when commands stop for command_timeout_s")
    col.health_of("io", lambda d: d["command_timed_out"] == "True", message="the timeout in health")

    refused = bus.set_config("io", "safe_levels", "horn=1")
    assert refused is not None and not refused.ok and "config 'safe_levels' names 'horn'" in refused.error

    command(bus, "lamp", 100.0)
    wait_until(lambda: chip.read_output(LAMP) == 1, message="lamp on again")
    proc.terminate()
    assert proc.wait(timeout=10) == 0
    assert (chip.read_output(LAMP), chip.read_output(BRAKE)) == (0, 1), "safe levels on SIGTERM"
    writes = [r for r in col.since(raw_channel("io")) if isinstance(r, t.RawGpioWrite)]
    assert {(w.line, w.value) for w in writes} >= {(LAMP, 0), (LAMP, 1), (BRAKE, 0), (BRAKE, 1)}


def test_a_lost_chip_is_reported_commands_are_counted_and_outputs_restart_safe(
        chip: MockGpioChip, tmp_path: Path, services: ServiceProcesses, bus: BusClient) -> None:
    col = BusCollector(bus).listen(ch.HEALTH, t.Health)
    proc = start(services, tmp_path, name="io", kind="gpio_output",
                 socket=chip.socket_path, settings={"outputs": "lamp=17,brake=18", "safe_levels": "brake=1",
                           "command_timeout_s": 0.0, "rc_gating": False})
    wait_until(lambda: chip.consumers().get(LAMP) == "u2sa:io", message="the lines requested", timeout=30)
    command(bus, "lamp", 100.0)
    command(bus, "brake", 0.0)
    wait_until(lambda: (chip.read_output(LAMP), chip.read_output(BRAKE)) == (1, 0), message="lamp on, brake off")

    chip.stop()                              # the chip goes away under the driver, no write pending
    details = col.health_of("io", lambda d: d["port"] == "down", since=col.count(ch.HEALTH),
                            message="the lost chip in health")
    assert details["status"] == "degraded" and details["port_losses"] == "1"
    assert "mock chip" in details["port_error"] and "start the mock chip" in details["port_error"]
    command(bus, "lamp", 0.0)                # cannot be applied while the chip is gone: counted
    details = col.health_of("io", lambda d: d["unapplied"] == "1", since=col.count(ch.HEALTH),
                            message="the command that could not be applied")
    assert details["port"] == "down" and details["lamp"] == "unknown" and proc.poll() is None

    again = MockGpioChip(socket_path=chip.socket_path, release_level=None).start()
    try:
        wait_until(lambda: again.consumers().get(LAMP) == "u2sa:io", message="the lines requested again")
        assert (again.read_output(LAMP), again.read_output(BRAKE)) == (0, 1), "re-requested at the safe levels"
        details = col.health_of("io", lambda d: d["port"] == "open", since=col.count(ch.HEALTH))
        assert details["status"] == "ok" and details["port_losses"] == "1" and details["port_error"] == ""
        assert (details["lamp"], details["brake"]) == ("0", "1")
        command(bus, "lamp", 100.0)
        wait_until(lambda: again.read_output(LAMP) == 1, message="commands obeyed on the new chip")
        proc.terminate()
        assert proc.wait(timeout=10) == 0
        assert (again.read_output(LAMP), again.read_output(BRAKE)) == (0, 1), "safe levels on SIGTERM"
    finally:
        again.stop()


@pytest.fixture
def inputs_service(chip: MockGpioChip, tmp_path: Path, services: ServiceProcesses,
                   bus: BusClient) -> Iterator[tuple[BusCollector, subprocess.Popen]]:
    col = BusCollector(bus).listen(ch.HEALTH, t.Health).listen(ch.FAILSAFE, t.Failsafe)
    col.listen(ch.OBJECTS, t.ObjectDescription)
    settings = {"inputs": "estop=4,bump=22,door=23", "bias": "pull-up",
                "active_low": "estop,bump", "failsafe_on": "estop", "positions": "bump=0.45:-0.1:0.2",
                "failsafe_repeat_s": 0.3, "bumper_repeat_s": 0.3, "debounce_ms": 5.0}
    proc = start(services, tmp_path, name="sw", kind="gpio_input", settings=settings, socket=chip.socket_path)
    col.health_of("sw", lambda d: d["port"] == "open", timeout=30, message="the inputs open")
    yield col, proc


def test_estop_commands_failsafe_and_bumpers_report_objects(chip: MockGpioChip, inputs_service: Any) -> None:
    col, proc = inputs_service
    details = col.health_of("sw", lambda d: d["port"] == "open")
    assert (details["estop"], details["bump"], details["door"]) == ("inactive", "inactive", "active")  # pull-ups
    assert col.count(ch.FAILSAFE) == 0 and col.count(ch.OBJECTS) == 0

    chip.drive_input(ESTOP, 0)      # normally closed e-stop opens: active low
    pressed = col.wait_for(ch.FAILSAFE, lambda m: m.active, message="FAILSAFE from the e-stop")
    assert "estop" in pressed.reason and pressed.service == "sw" and pressed.header.source == "sw"
    first = col.count(ch.FAILSAFE)
    col.wait_for(ch.FAILSAFE, lambda m: m.active, since=first, message="the failsafe repeated while held")
    chip.drive_input(ESTOP, 1)
    released = col.wait_for(ch.FAILSAFE, lambda m: not m.active, message="the failsafe cleared on release")
    assert "released" in released.reason

    chip.drive_input(BUMP, 0)
    hit = col.wait_for(ch.OBJECTS, lambda m: m.object_type == "bumper", message="a bumper object")
    assert (hit.uid, hit.reference_frame, hit.level, hit.source) == ("sw.bump", "FRD", 3, "sw")
    assert (hit.x, hit.y, hit.z) == (0.45, -0.1, 0.2)
    col.wait_for(ch.OBJECTS, lambda m: True, since=1, message="the bumper repeated while held")
    chip.drive_input(BUMP, 1)
    chip.drive_input(DOOR, 0)
    details = col.health_of("sw", lambda d: d["door"] == "inactive", since=col.count(ch.HEALTH))
    assert details["bump"] == "inactive" and int(details["estop_edges"]) == 2 and details["failsafe"] == "False"
    assert proc.poll() is None


def test_unreadable_estop_holds_the_failsafe_until_the_port_is_back(chip: MockGpioChip, inputs_service: Any) -> None:
    col, proc = inputs_service
    assert chip.disconnect("u2sa:sw") == 1
    down = col.wait_for(ch.FAILSAFE, lambda m: m.active, message="FAILSAFE while the e-stop cannot be read")
    assert "cannot be read" in down.reason
    col.wait_for(ch.FAILSAFE, lambda m: not m.active, message="cleared once the e-stop reads released again")
    details = col.health_of("sw", lambda d: d["port_losses"] == "1" and d["port"] == "open", since=0)
    assert details["estop"] == "inactive" and proc.poll() is None


def test_bad_input_config_stops_the_service_with_the_reason(tmp_path: Path, services: ServiceProcesses) -> None:
    proc = start(services, tmp_path, name="sw", kind="gpio_input",
                 settings={"inputs": "estop=4", "positions": "bump=1:0:0"}, socket="/nonexistent.sock")
    assert proc.wait(timeout=20) != 0
    assert "config 'positions' names 'bump', not a configured line" in (tmp_path / "sw.stderr").read_text()
