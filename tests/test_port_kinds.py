"""The kind table: every port kind is a package with every part, registered once (docs/ports.md, "Port kinds").

A walk over ``PORT_KINDS``: each kind implements the ``PortKind`` protocol, lives in its own
``u2sa_hw/ports/<kind>/`` package with its grammar, real backend, mock client, wire
protocol, probe and replay device, parses its own examples, refuses a parameter it does not take, and opens a missing
device (real and mock) as a ``PortUnavailable`` naming the device and the fix. A new kind that
leaves a part out fails here, not on a vehicle.
"""

from __future__ import annotations

import importlib
import tempfile
from importlib.util import find_spec
from pathlib import Path
from typing import Any, Iterator

import pytest

from u2sa_hw.ports import PortUnavailable
from u2sa_hw.ports.address import EXAMPLES, KINDS, MOCK_EXAMPLES, AddressError, parse_address
from u2sa_hw.ports.kinds import PORT_KINDS, port_kind
from u2sa_hw.ports.opener import open_port
from u2sa_hw.ports.port_kind import PortKind

PORTS = Path(__file__).resolve().parent.parent / "u2sa_hw" / "ports"
PACKAGES = ("serial", "can", "i2c", "gpio", "pwm")

# the wire end each kind's mock device serves: the codec both ends share
WIRE = {
    "serial": ("u2sa_hw.ports.serial.clock", "encode_frame"),       # a pty; a replay's stamped frames
    "can": ("u2sa_hw.ports.can.clock", "pack_frame"),               # udp_multicast datagrams
    "i2c": ("u2sa_hw.ports.i2c.wire", "REQUEST"),                   # the mock bus's request/response
    "gpio": ("u2sa_hw.ports.gpio.wire", "MockFrameReader"),         # the mock chip's frames
    "pwm": ("u2sa_hw.ports.pwm.port", "make_sysfs_pwm_tree"),       # a sysfs-shaped tree
    "pca9685": ("u2sa_hw.ports.i2c.wire", "REQUEST"),               # a chip model on the mock I2C bus
}
# what opening a device of the kind needs besides its address (the lines a GPIO request asks for)
OPEN_OPTIONS: dict[str, dict[str, Any]] = {"gpio": {"inputs": [5]}}
# an option no kind takes, refused by every kind that lists its options
UNKNOWN_OPTION = {"bogus_option": 1}


@pytest.fixture()
def sockets() -> Iterator[Path]:
    """A short directory for would-be Unix sockets and ptys (their paths are limited to 108 bytes)."""
    path = Path(tempfile.mkdtemp(prefix="u2k", dir="/tmp"))
    yield path
    path.rmdir()


def missing_real(kind: str) -> str:
    """A real address of *kind* that names no device on this machine."""
    return {"serial": "serial:///dev/u2sa-missing-tty?baud=9600", "can": "can://socketcan/u2sa-missing0",
            "i2c": "i2c://97/0x68", "gpio": "gpio://gpiochip97/5", "pwm": "pwm://pwmchip97/0",
            "pca9685": "pca9685://97/0x40/0"}[kind]


def missing_mock(kind: str, where: Path) -> str | None:
    """A mock address of *kind* that nothing serves (None: the kind's mock buses are made on open)."""
    return {"serial": f"mock+serial://{where}/gps", "can": None, "i2c": f"mock+i2c://{where}/i2c.sock/0x68",
            "gpio": f"mock+gpio://{where}/chip.sock/5", "pwm": f"mock+pwm://{where}/pwmchip0/0",
            "pca9685": f"mock+pca9685://{where}/i2c.sock/0x40/0"}[kind]


def test_the_table_is_the_one_list_of_kinds() -> None:
    assert set(PORT_KINDS) == {"serial", "can", "i2c", "gpio", "pwm", "pca9685"}
    assert KINDS == tuple(PORT_KINDS)
    assert EXAMPLES == {name: kind.example for name, kind in PORT_KINDS.items()}
    assert MOCK_EXAMPLES == {name: kind.mock_example for name, kind in PORT_KINDS.items()}
    assert {kind.package for kind in PORT_KINDS.values()} == {f"u2sa_hw.ports.{p}" for p in PACKAGES}
    with pytest.raises(KeyError, match="known: serial, can"):
        port_kind("spi")


def test_every_package_is_a_folder_with_its_grammar_and_kind() -> None:
    for package in PACKAGES:
        folder = PORTS / package
        assert {"__init__.py", "grammar.py", "kind.py"} <= {p.name for p in folder.glob("*.py")}, folder
        assert importlib.import_module(f"u2sa_hw.ports.{package}").__doc__
    stale = sorted(p.name for p in PORTS.glob("*_port.py"))
    assert stale == [], f"a per-kind module outside its package: {stale}"


@pytest.mark.parametrize("name", sorted(PORT_KINDS))
class TestEveryKind:
    def test_it_implements_the_protocol_in_its_package(self, name: str) -> None:
        kind = PORT_KINDS[name]
        assert isinstance(kind, PortKind)
        assert kind.name == name
        assert type(kind).__module__ == f"{kind.package}.kind"
        assert type(kind).__doc__ and kind.real_backend and kind.mock_backend
        for method in ("parse", "open_real", "open_mock"):
            assert getattr(type(kind), method).__doc__, f"{name}.{method} has no docstring"

    def test_it_parses_its_examples(self, name: str) -> None:
        kind = PORT_KINDS[name]
        real = parse_address(kind.example, device="dev")
        mock = parse_address(kind.mock_example, device="dev")
        assert (real.kind, real.mock, real.scheme) == (name, False, name)
        assert (mock.kind, mock.mock, mock.scheme) == (name, True, f"mock+{name}")

    def test_it_refuses_a_parameter_it_does_not_take(self, name: str) -> None:
        kind = PORT_KINDS[name]
        joiner = "&" if "?" in kind.example else "?"
        with pytest.raises(AddressError, match=f"unknown parameter 'bogus'.*{name} addresses take"):
            parse_address(f"{kind.example}{joiner}bogus=1", device="dev")
        for param in kind.params:
            assert param.isidentifier()

    def test_its_backends_and_wire_exist(self, name: str) -> None:
        kind = PORT_KINDS[name]
        assert kind.preload and all(find_spec(module) is not None for module in kind.preload)
        assert any(module.startswith(kind.package) for module in kind.preload)
        module, attribute = WIRE[name]
        assert hasattr(importlib.import_module(module), attribute)

    def test_a_missing_real_device_is_port_unavailable_with_the_fix(self, name: str) -> None:
        with pytest.raises(PortUnavailable) as info:
            open_port(missing_real(name), device="thing", **OPEN_OPTIONS.get(name, {}))
        assert info.value.device == "thing" and info.value.fix

    def test_a_missing_mock_device_is_port_unavailable_with_the_fix(self, name: str, sockets: Path) -> None:
        address = missing_mock(name, sockets)
        if address is None:
            pytest.skip(f"{name}: a mock bus is made when it is opened; it cannot be missing")
        with pytest.raises(PortUnavailable) as info:
            open_port(address, device="thing", **OPEN_OPTIONS.get(name, {}))
        assert info.value.device == "thing" and info.value.fix

    def test_an_option_it_does_not_take_is_a_type_error(self, name: str, sockets: Path) -> None:
        kind = PORT_KINDS[name]
        if kind.options is None:
            pytest.skip(f"{name} hands any option to its library")
        address = missing_mock(name, sockets) or kind.mock_example
        with pytest.raises(TypeError, match="bogus_option"):
            open_port(address, device="thing", **OPEN_OPTIONS.get(name, {}), **UNKNOWN_OPTION)


def test_the_typed_address_reaches_the_pca9685_backend_without_a_string(monkeypatch: pytest.MonkeyPatch) -> None:
    """No ``pca9685:<bus>:<addr>`` text is rebuilt from a parsed address, and nothing parses it again."""
    from u2sa_hw.ports.pwm import pca9685

    calls: list[dict[str, Any]] = []
    monkeypatch.setattr(pca9685, "open_pca9685_channel", lambda **kwargs: calls.append(kwargs) or "channel")
    monkeypatch.setattr(pca9685, "parse_address", lambda *a, **k: pytest.fail("the address was parsed again"))
    assert open_port("mock+pca9685:///run/x.sock/0x41/3", device="rudder", period_ns=3_000_000) == "channel"
    assert open_port("pca9685://1/0x40/15", device="rudder") == "channel"
    assert calls == [
        dict(device="rudder", address="mock+pca9685:///run/x.sock/0x41/3", bus="/run/x.sock", i2c_address=0x41,
             channel=3, period_ns=3_000_000, tap=None),
        dict(device="rudder", address="pca9685://1/0x40/15", bus=1, i2c_address=0x40, channel=15,
             period_ns=20_000_000, tap=None)]


def test_the_serial_backend_is_told_path_or_url_by_the_address(monkeypatch: pytest.MonkeyPatch) -> None:
    """``open_serial`` gets ``pyserial_url`` from the parsed address, not from ``"://" in`` the text."""
    from u2sa_hw.ports.serial import opener

    calls: list[dict[str, Any]] = []
    monkeypatch.setattr(opener, "open_serial", lambda path, **kwargs: calls.append({"path": path, **kwargs}))
    open_port("serial+socket://localhost:7000?baud=19200", device="gps")
    open_port("serial:///dev/u2sa/gps", device="gps")
    assert [(c["path"], c["pyserial_url"], c["baudrate"]) for c in calls] == [
        ("socket://localhost:7000", True, 19200), ("/dev/u2sa/gps", False, 9600)]


@pytest.mark.parametrize("name", sorted(PORT_KINDS))
def test_every_kind_has_a_read_only_probe_in_its_package(name: str) -> None:
    """``u2sa check --probe`` finds each kind's probe through the table: its name, its parameters, the probe."""
    from u2sa_hw.check.probe import PROBES
    from u2sa_hw.check.targets import TARGETS

    kind = PORT_KINDS[name]
    assert kind.probe is not None and kind.probe.startswith("u2sa_hw.ports.") and kind.probe.endswith(".probe")
    module = importlib.import_module(kind.probe)
    assert module.__doc__ and module.target_params.__doc__ and module.probe.__doc__
    assert PROBES[module.PROBE] is module.probe and name in TARGETS
    target = TARGETS[name]("dev", "svc", parse_address(kind.example, device="dev"), {})
    assert (target.port, target.address) == (module.PROBE, kind.example) and target.params


@pytest.mark.parametrize("name", sorted(PORT_KINDS))
def test_what_install_makes_of_a_kind_is_in_its_package(name: str) -> None:
    """``u2sa install`` finds what a real address of each kind needs through the table (None: nothing)."""
    kind = PORT_KINDS[name]
    expected = {"serial": "u2sa_hw.ports.serial.install", "can": "u2sa_hw.ports.can.install",
                "pwm": "u2sa_hw.ports.pwm.install"}.get(name)
    assert kind.install == expected
    if kind.install is not None:
        module = importlib.import_module(kind.install)
        assert module.__doc__ and module.plan_device.__doc__


# the replay device each kind's ``replay`` part names: the class a replay of a RAW.<device> of the kind plays into
REPLAY = {
    "serial": "ReplaySerialDevice", "can": "ReplayCanDevice", "i2c": "ReplayI2cDevice",
    "gpio": "ReplayGpioDevice", "pwm": "ReplayPwmDevice", "pca9685": "ReplayPwmDevice",
}


@pytest.mark.parametrize("name", sorted(PORT_KINDS))
def test_every_kind_names_its_replay_device(name: str, tmp_path: Path) -> None:
    """``u2sa replay`` finds each kind's replay device through the table: a ``module:factory`` string (``u2sa_hw``
    never imports ``hil``), a documented factory that makes the kind's device from a device of the log."""
    from u2sa_hw.hil.replay_buses import make_device
    from u2sa_hw.hil.replay_plan import REPLAYABLE, DevicePlan, ServicePlan
    from u2sa_hw.ports.port_kind import load_part

    kind = PORT_KINDS[name]
    assert isinstance(kind.replay, str) and kind.replay.startswith("u2sa_hw.")
    factory = load_part(kind.replay)
    assert callable(factory) and factory.__doc__
    assert name in REPLAYABLE
    service = ServicePlan("svc", "gps_nmea" if name == "serial" else "gpio_input", {})
    device = factory(DevicePlan(name="dev", kind=name, records=0), tmp_path, service=service, fast=True, rigs={})
    assert type(device).__name__ == REPLAY[name] and device.name == "dev"
    raw_kind = "pwm" if name == "pca9685" else name   # a PCA9685's records are RawPwmWrite: a pwm device in a log
    through = make_device(DevicePlan(name="dev2", kind=raw_kind, records=0), tmp_path, service, fast=True, rigs={})
    assert type(through).__name__ == REPLAY[name]


def test_a_kind_part_is_module_colon_name() -> None:
    from u2sa_hw.ports.port_kind import load_part

    with pytest.raises(ValueError, match="expected 'module:name'"):
        load_part("u2sa_hw.hil.replay_buses.make_i2c_device")
