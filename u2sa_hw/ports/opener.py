"""``open_port(address, *, device, tap=None, **options)``: one scheme table picks the opener.

Like python-can's ``BACKENDS`` and pyserial's ``serial_for_url``, the scheme of a device
address (:mod:`u2sa_hw.ports.address`) is looked up in :data:`SCHEMES`, which names the
function that opens it; the function's module is imported only then, so a GPS service
never imports python-can. ``serial+X`` schemes use the ``serial`` entry (pyserial picks X).

Options a kind takes (everything else about the device is in its address):

======== ==================================================================================
serial   ``timeout`` (read timeout, s)
can      any ``can.Bus`` keyword (added to the address's parameters)
i2c      none (a mock+i2c address may carry ``timeout=S``: the client's answer timeout)
gpio     ``inputs`` (line offsets), ``outputs`` (line -> initial value), ``edge``, ``bias``;
         each line must be one the address lists (when it lists any)
pwm      ``period_ns``
pca9685  ``period_ns``
======== ==================================================================================

Errors: :class:`~u2sa_hw.ports.address.AddressError` for a malformed address or a line the
address does not list (a config error), :class:`~u2sa_hw.ports.errors.PortUnavailable` when
the device cannot be opened (with the fix).
"""

from __future__ import annotations

import importlib
from typing import Any, Callable

from u2sa_hw.ports.address import AddressError, DeviceAddress, parse_address
from u2sa_hw.ports.tap import Tap

# scheme -> (what opens it, description for docs and `u2sa check`)
SCHEMES: dict[str, tuple[str, str]] = {
    "serial": ("u2sa_hw.ports.opener:_open_serial", "a serial device node (pyserial, exclusive) or pyserial URL"),
    "mock+serial": ("u2sa_hw.ports.opener:_open_serial", "a pty whose other end a mock device holds"),
    "can": ("u2sa_hw.ports.opener:_open_can", "python-can interface/channel (socketcan on a vehicle)"),
    "mock+can": ("u2sa_hw.ports.opener:_open_can", "python-can udp_multicast/virtual bus with mock nodes"),
    "i2c": ("u2sa_hw.ports.opener:_open_i2c", "smbus2 on /dev/i2c-N"),
    "mock+i2c": ("u2sa_hw.ports.opener:_open_i2c", "the mock I2C bus server's Unix socket"),
    "gpio": ("u2sa_hw.ports.opener:_open_gpio", "libgpiod v2 on /dev/gpiochipN"),
    "mock+gpio": ("u2sa_hw.ports.opener:_open_gpio", "the mock GPIO chip's Unix socket"),
    "pwm": ("u2sa_hw.ports.opener:_open_pwm", "sysfs /sys/class/pwm/pwmchipN"),
    "mock+pwm": ("u2sa_hw.ports.opener:_open_pwm", "a sysfs-shaped directory"),
    "pca9685": ("u2sa_hw.ports.opener:_open_pwm", "a PCA9685 channel over smbus2"),
    "mock+pca9685": ("u2sa_hw.ports.opener:_open_pwm", "a PCA9685 model on the mock I2C bus"),
}


# What opening a device of each kind imports beyond its opener: the port module and the library under it
# (python-can alone is some 160 modules). ``preload`` imports them when the driver sets up, before its
# READY=1 arms the watchdog; left to the first open, in the service's first loop turn, that import took
# over 2 s without a ping on a loaded machine and the launcher killed a healthy motor driver.
PRELOAD: dict[str, tuple[str, ...]] = {
    "serial": ("u2sa_hw.ports.serial.opener",),
    "can": ("u2sa_hw.ports.can.port", "can", "u2sa_hw.ports.can.clock"),
    "i2c": ("u2sa_hw.ports.i2c.port",),
    "gpio": ("u2sa_hw.ports.gpio.port", "u2sa_hw.ports.gpio.mock_client", "u2sa_hw.ports.gpio.gpiod_backend"),
    "pwm": ("u2sa_hw.ports.pwm.port",),
    "pca9685": ("u2sa_hw.ports.pwm.port", "u2sa_hw.ports.pwm.pca9685"),
}


def preload(address: DeviceAddress) -> None:
    """Import what opening *address* will import, now (a missing library is left for the open to report)."""
    for module in PRELOAD.get(address.kind, ()):
        try:
            importlib.import_module(module)
        except ImportError:
            pass   # the open raises PortUnavailable naming the library and the fix


def table_key(address: DeviceAddress) -> str:
    """The :data:`SCHEMES` key of *address* (``serial+socket`` -> ``serial``)."""
    return ("mock+" if address.mock else "") + address.kind


def _resolve(target: str) -> Callable[..., Any]:
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)


def open_port(address: DeviceAddress | str, *, device: str, tap: Tap | None = None, **options: Any) -> Any:
    """Open the device at *address* as *device* (its name in errors and taps); see the module docstring."""
    if isinstance(address, str):
        address = parse_address(address, device=device)
    target, _ = SCHEMES[table_key(address)]
    return _resolve(target)(address, device=device, tap=tap, **options)


def _unknown_options(address: DeviceAddress, device: str, options: dict[str, Any], allowed: tuple[str, ...]) -> None:
    extra = sorted(set(options) - set(allowed))
    if extra:
        raise TypeError(f"{device}: open_port({address.kind}) takes {', '.join(allowed) or 'no options'}, "
                        f"not {', '.join(extra)}")


def _open_serial(address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> Any:
    from u2sa_hw.ports.serial.opener import open_serial

    _unknown_options(address, device, options, ("timeout",))
    stop = address.stopbits
    return open_serial(address.serial_path, device=device, baudrate=address.baud, bytesize=address.bytesize,
                       parity=address.parity, stopbits=int(stop) if stop.is_integer() else stop,
                       timeout=options.get("timeout", 0.1), tap=tap, device_clock=address.device_clock)


def _open_can(address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> Any:
    from u2sa_hw.ports.can.port import open_can

    bus_options = {**address.bus_options, **options}
    return open_can(device=device, interface=address.can_interface, channel=address.can_channel,
                    bitrate=address.bitrate, tap=tap, **bus_options)


def _open_i2c(address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> Any:
    from u2sa_hw.ports.i2c.port import open_i2c

    _unknown_options(address, device, options, ())
    return open_i2c(device=device, bus=address.i2c_bus, address=address.chip_address, tap=tap,
                    timeout=address.i2c_timeout)


def _open_gpio(address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> Any:
    from u2sa_hw.ports.gpio.port import open_gpio

    _unknown_options(address, device, options, ("inputs", "outputs", "edge", "bias"))
    inputs = list(options.get("inputs", ()))
    outputs = dict(options.get("outputs") or {})
    if address.lines:
        missing = sorted((set(inputs) | set(outputs)) - set(address.lines))
        if missing:
            listed = ",".join(str(n) for n in sorted({*address.lines, *missing}))
            raise AddressError(device, address.url, f"line(s) {', '.join(map(str, missing))} are used but not "
                               f"listed; list every line the device uses (…/{listed})", kind="gpio")
    extra = {k: options[k] for k in ("edge", "bias") if k in options}
    return open_gpio(device=device, chip=address.gpio_chip, inputs=inputs, outputs=outputs, tap=tap, **extra)


def _open_pwm(address: DeviceAddress, *, device: str, tap: Tap | None, **options: Any) -> Any:
    from u2sa_hw.ports.pwm.port import open_pwm

    _unknown_options(address, device, options, ("period_ns",))
    return open_pwm(device=device, address=address.pwm_legacy_address, channel=address.pwm_channel,
                    period_ns=options.get("period_ns", 20_000_000), tap=tap)
