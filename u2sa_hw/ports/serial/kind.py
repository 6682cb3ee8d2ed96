"""The serial port kind: ``serial://`` (a device node), ``serial+X://`` (a pyserial URL), ``mock+serial://`` (a pty).

Options ``open_port`` passes on: ``timeout`` (the read timeout, s).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from u2sa_hw.ports.address_schemes import Fail, Parsed, UrlParts
from u2sa_hw.ports.port_kind import check_options
from u2sa_hw.ports.serial.grammar import SERIAL_PARAMS, parse_serial

if TYPE_CHECKING:
    from u2sa_hw.ports.address import DeviceAddress
    from u2sa_hw.ports.serial.port import SerialPort
    from u2sa_hw.ports.tap import Tap


class SerialKind:
    """Serial devices through pyserial; the mock is a pty whose other end a mock device holds."""

    name = "serial"
    package = "u2sa_hw.ports.serial"
    example = "serial:///dev/u2sa/gps?baud=9600"
    mock_example = "mock+serial:///run/sim/gps?baud=9600"
    real_backend = "a serial device node (pyserial, exclusive) or pyserial URL"
    mock_backend = "a pty whose other end a mock device holds"
    params = SERIAL_PARAMS
    options: tuple[str, ...] | None = ("timeout",)
    preload = ("u2sa_hw.ports.serial.opener",)
    probe: str | None = "u2sa_hw.ports.serial.probe"
    install: str | None = "u2sa_hw.ports.serial.install"
    replay = "u2sa_hw.hil.replay_devices:make_serial_device"   # a pty, the recorded reads on their stamps

    def parse(self, parts: UrlParts, fail: Fail) -> Parsed:
        """See :func:`u2sa_hw.ports.serial.grammar.parse_serial`."""
        return parse_serial(parts, fail)

    def open_real(self, address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> SerialPort:
        """The device node, or the pyserial URL of a ``serial+X://`` address."""
        return self._open(address, device=device, tap=tap, **options)

    def open_mock(self, address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> SerialPort:
        """The pty a mock device holds (stamped frames with ``clock=stamped``: a replay's device clock)."""
        return self._open(address, device=device, tap=tap, **options)

    def _open(self, address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> SerialPort:
        from u2sa_hw.ports.serial.opener import open_serial

        check_options(self, address, device, options)
        stop = address.stopbits
        return open_serial(address.serial_path, device=device, baudrate=address.baud, bytesize=address.bytesize,
                           parity=address.parity, stopbits=int(stop) if stop.is_integer() else stop,
                           timeout=options.get("timeout", 0.1), tap=tap, device_clock=address.device_clock,
                           pyserial_url=address.is_serial_url)


SERIAL = SerialKind()
