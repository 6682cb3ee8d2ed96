"""The PWM port kinds: ``pwm://pwmchipN/CHANNEL`` (sysfs), ``pca9685://BUS/CHIP/CHANNEL`` (a PCA9685 on I2C).

Both hand out a :class:`~u2sa_hw.ports.pwm.port.PwmChannel`; their mocks are a sysfs-shaped
directory (``mock+pwm``) and a PCA9685 model on the mock I2C bus (``mock+pca9685``). Options
``open_port`` passes on: ``period_ns`` (the frame period, default 20 ms; a ValueError unless > 0).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from u2sa_hw.ports.address_schemes import Fail, Parsed, UrlParts
from u2sa_hw.ports.i2c.grammar import parse_i2c
from u2sa_hw.ports.port_kind import check_options
from u2sa_hw.ports.pwm.grammar import PCA9685_PARAMS, PWM_PARAMS, parse_pwm

if TYPE_CHECKING:
    from u2sa_hw.ports.address import DeviceAddress
    from u2sa_hw.ports.pwm.port import PwmChannel
    from u2sa_hw.ports.tap import Tap

DEFAULT_PERIOD_NS = 20_000_000   # 50 Hz: servos and ESCs


def period_option(device: str, options: dict[str, Any]) -> int:
    """The ``period_ns`` option (default 20 ms); ValueError naming *device* unless it is > 0."""
    period_ns = options.get("period_ns", DEFAULT_PERIOD_NS)
    if period_ns <= 0:
        raise ValueError(f"{device}: period_ns must be > 0, got {period_ns}")
    return period_ns


class PwmKind:
    """A Linux sysfs PWM channel; the mock is a sysfs-shaped directory the simulation reads."""

    name = "pwm"
    package = "u2sa_hw.ports.pwm"
    example = "pwm://pwmchip0/0"
    mock_example = "mock+pwm:///run/sim/pwmchip0/0"
    real_backend = "sysfs /sys/class/pwm/pwmchipN"
    mock_backend = "a sysfs-shaped directory"
    params = PWM_PARAMS
    options: tuple[str, ...] | None = ("period_ns",)
    preload = ("u2sa_hw.ports.pwm.port",)
    probe: str | None = "u2sa_hw.ports.pwm.probe"
    install: str | None = "u2sa_hw.ports.pwm.install"
    replay = "u2sa_hw.hil.replay_buses:make_pwm_device"   # a sysfs-shaped directory per recorded chip

    def parse(self, parts: UrlParts, fail: Fail) -> Parsed:
        """See :func:`u2sa_hw.ports.pwm.grammar.parse_pwm`."""
        return parse_pwm(parts, fail)

    def open_real(self, address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> PwmChannel:
        """The channel of the kernel's chip under /sys/class/pwm."""
        return self._open(address, device=device, tap=tap, **options)

    def open_mock(self, address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> PwmChannel:
        """The channel of a sysfs-shaped directory (the backend plays the kernel's part)."""
        return self._open(address, device=device, tap=tap, **options)

    def _open(self, address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> PwmChannel:
        from u2sa_hw.ports.pwm.port import open_sysfs_pwm

        check_options(self, address, device, options)
        return open_sysfs_pwm(device=device, address=address.pwm_chip, channel=address.pwm_channel,
                              period_ns=period_option(device, options), tap=tap)


class Pca9685Kind:
    """One output of a PCA9685 on an I2C bus; the mock is a PCA9685 model on the mock I2C bus."""

    name = "pca9685"
    package = "u2sa_hw.ports.pwm"
    example = "pca9685://1/0x40/3"
    mock_example = "mock+pca9685:///run/sim/i2c-1.sock/0x40/3"
    real_backend = "a PCA9685 channel over smbus2"
    mock_backend = "a PCA9685 model on the mock I2C bus"
    params = PCA9685_PARAMS
    options: tuple[str, ...] | None = ("period_ns",)
    preload = ("u2sa_hw.ports.pwm.port", "u2sa_hw.ports.pwm.pca9685")
    probe: str | None = "u2sa_hw.ports.i2c.probe"   # one identity read per chip
    install: str | None = None   # an I2C chip: udev/60-u2sa-permissions.rules covers its adapter
    replay = "u2sa_hw.hil.replay_buses:make_pwm_device"   # a PCA9685 model on a mock I2C bus

    def parse(self, parts: UrlParts, fail: Fail) -> Parsed:
        """See :func:`u2sa_hw.ports.i2c.grammar.parse_i2c` (an I2C bus and chip, then the channel)."""
        return parse_i2c(parts, fail)

    def open_real(self, address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> PwmChannel:
        """The output of the chip on adapter ``/dev/i2c-N``."""
        return self._open(address, int(address.location), device=device, tap=tap, **options)

    def open_mock(self, address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> PwmChannel:
        """The output of the PCA9685 model on the mock bus server at the address's socket."""
        return self._open(address, address.location, device=device, tap=tap, **options)

    def _open(self, address: DeviceAddress, bus: int | str, *, device: str, tap: Tap | None,
              **options: Any) -> PwmChannel:
        from u2sa_hw.ports.pwm.pca9685 import open_pca9685_channel

        check_options(self, address, device, options)
        return open_pca9685_channel(device=device, address=address.url, bus=bus, i2c_address=address.chip_address,
                                    channel=address.pwm_channel, period_ns=period_option(device, options), tap=tap)


PWM = PwmKind()
PCA9685 = Pca9685Kind()
