"""The I2C port kind: ``i2c://BUS/CHIP`` (smbus2 on ``/dev/i2c-BUS``), ``mock+i2c:///BUS.sock/CHIP`` (the mock bus).

``open_port`` passes no options on: a mock address carries the client's ``timeout=`` itself.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from u2sa_hw.ports.address_schemes import Fail, Parsed, UrlParts
from u2sa_hw.ports.i2c.grammar import I2C_PARAMS, parse_i2c
from u2sa_hw.ports.port_kind import check_options

if TYPE_CHECKING:
    from u2sa_hw.ports.address import DeviceAddress
    from u2sa_hw.ports.i2c.port import I2cPort
    from u2sa_hw.ports.tap import Tap


class I2cKind:
    """One chip on an I2C bus; the mock is the mock I2C bus server's Unix socket (:mod:`u2sa_hw.ports.i2c.wire`)."""

    name = "i2c"
    package = "u2sa_hw.ports.i2c"
    example = "i2c://1/0x68"
    mock_example = "mock+i2c:///run/sim/i2c-1.sock/0x68"
    real_backend = "smbus2 on /dev/i2c-N"
    mock_backend = "the mock I2C bus server's Unix socket"
    params = I2C_PARAMS
    options: tuple[str, ...] | None = ()
    preload = ("u2sa_hw.ports.i2c.port",)
    probe: str | None = "u2sa_hw.ports.i2c.probe"
    install: str | None = None   # udev/60-u2sa-permissions.rules covers every adapter
    replay = "u2sa_hw.hil.replay_buses:make_i2c_device"   # a mock bus with the recorded reads

    def parse(self, parts: UrlParts, fail: Fail) -> Parsed:
        """See :func:`u2sa_hw.ports.i2c.grammar.parse_i2c`."""
        return parse_i2c(parts, fail)

    def open_real(self, address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> I2cPort:
        """The chip on adapter ``/dev/i2c-N`` (smbus2)."""
        from u2sa_hw.ports.i2c.port import open_i2c_chip

        check_options(self, address, device, options)
        return open_i2c_chip(device=device, bus=int(address.location), chip=address.chip_address, tap=tap)

    def open_mock(self, address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> I2cPort:
        """The chip on the mock bus server at the address's socket, waiting ``timeout=`` for each answer."""
        from u2sa_hw.ports.i2c.port import open_i2c_chip

        check_options(self, address, device, options)
        return open_i2c_chip(device=device, bus=address.location, chip=address.chip_address, tap=tap,
                             timeout=address.i2c_timeout)


I2C = I2cKind()
