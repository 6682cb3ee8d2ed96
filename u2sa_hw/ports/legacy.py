"""Addresses from the old per-kind settings, for drivers' ``used_devices`` and DeviceLinks.

Profiles written before ``[devices.NAME] address`` spread an address over driver settings
(``port`` + ``baudrate``; ``bus`` + ``address``; ``interface`` + ``channel`` + ``bitrate``;
``chip`` + lines; a PWM channel's ``address`` + ``channel``). Each function here turns one
such set of values into the address text of the new form, or None when they name no device.
The drivers call them with their own settings; nothing else knows those names.
"""

from __future__ import annotations

from typing import Iterable

from u2sa_hw.ports.address import SYSFS_PWM, make_address

_MOCK = "mock:"


def serial_address(port: str, *, baudrate: int | None = None, bytesize: int = 8, parity: str = "N",
                   stopbits: float = 1.0) -> str | None:
    """``/dev/ttyUSB0`` + 9600 8N1 -> ``serial:///dev/ttyUSB0?baud=9600``; a pyserial URL -> ``serial+X://``."""
    port = (port or "").strip()
    if not port:
        return None
    params: dict[str, object] = {}
    if baudrate:
        params["baud"] = int(baudrate)
    if bytesize != 8:
        params["bytesize"] = int(bytesize)
    if str(parity).upper() != "N":
        params["parity"] = str(parity).upper()
    if float(stopbits) != 1.0:
        params["stopbits"] = f"{float(stopbits):g}"
    if "://" in port:
        return make_address("serial", port, params=params, backend=port.split("://", 1)[0]).url
    return make_address("serial", port, params=params).url


def can_address(interface: str, channel: str, *, bitrate: int | None = None, udp_port: int | None = None) -> str | None:
    """``socketcan`` + ``can0`` + 500000 -> ``can://socketcan/can0?bitrate=500000``."""
    if not interface or not channel:
        return None
    params: dict[str, object] = {}
    if bitrate:
        params["bitrate"] = int(bitrate)
    if udp_port and interface == "udp_multicast":
        params["port"] = int(udp_port)
    return make_address("can", str(channel), params=params, backend=str(interface)).url


def i2c_address(bus: int | str, chip: int) -> str | None:
    """Bus ``"1"`` + 0x68 -> ``i2c://1/0x68``; ``"mock:/x.sock"`` -> ``mock+i2c:///x.sock/0x68``."""
    text = str(bus).strip()
    if text.startswith(_MOCK):
        return make_address("i2c", text[len(_MOCK):], (int(chip),), mock=True).url
    if not text:
        return None
    return make_address("i2c", text, (int(chip),)).url


def gpio_address(chip: str, lines: Iterable[int] = ()) -> str | None:
    """``/dev/gpiochip0`` + lines -> ``gpio://gpiochip0/5,6``; ``mock:/x.sock`` -> ``mock+gpio:///x.sock/5,6``."""
    text = (chip or "").strip()
    if not text:
        return None
    numbers = tuple(sorted({int(n) for n in lines if int(n) >= 0}))
    if text.startswith(_MOCK):
        return make_address("gpio", text[len(_MOCK):], numbers, mock=True).url
    return make_address("gpio", text, numbers).url


def pwm_address(address: str, channel: int) -> str | None:
    """A PWM channel: a sysfs chip directory (outside /sys: a mock) or ``pca9685:<bus>:<chip>``."""
    text = (address or "").strip()
    if not text:
        return None
    if text.startswith("pca9685:"):
        bus, _, chip = text[len("pca9685:"):].rpartition(":")
        number = int(chip, 0)
        if bus.startswith(_MOCK):
            return make_address("pca9685", bus[len(_MOCK):], (number, int(channel)), mock=True).url
        return make_address("pca9685", bus, (number, int(channel))).url
    mock = not (text == SYSFS_PWM or text.startswith(SYSFS_PWM + "/"))
    return make_address("pwm", text.rstrip("/"), (int(channel),), mock=mock).url
