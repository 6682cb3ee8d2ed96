"""The per-scheme half of device addresses: the query parameters each kind takes and the parser of each body.

:func:`u2sa_hw.ports.address.parse_address` splits ``scheme://body?query`` and hands the
parts to :data:`PARSERS` (one function per kind); each returns ``(backend, location,
numbers)`` or raises the error its *fail* callback builds (an
:class:`~u2sa_hw.ports.address.AddressError` naming the device, the address and the fix).

Every kind takes a fixed set of query parameters (:data:`PARAMS`); any other is refused
with a did-you-mean, so a typo such as ``bitrat=500000`` is an error, not a value handed on
silently. CAN's set is the python-can bus options that fit in a URL (:data:`CAN_PARAMS`);
an interface that needs another adds it there (docs/ports.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Mapping

SYSFS_PWM = "/sys/class/pwm"
MOCK_PREFIX = "mock+"

SERIAL_PARAMS = ("baud", "bytesize", "parity", "stopbits", "usb", "serial", "clock")
SERIAL_CLOCKS = ("stamped",)   # clock=stamped: a replay's pty writes stamped frames (mock+serial only)
# python-can bus options (can.Bus keyword arguments) an address may carry; bitrate is the interface's
# bit rate (SocketCAN: set by u2sa install at boot), port/hop_limit are udp_multicast's, the rest
# socketcan's and virtual's (python-can 4.x).
CAN_PARAMS = ("bitrate", "data_bitrate", "fd", "receive_own_messages", "local_loopback", "ignore_rx_error_frames",
              "port", "hop_limit", "rx_queue_size", "preserve_timestamps", "clock")
CAN_CLOCKS = ("stamped",)      # clock=stamped: a replay's frames carry their recorded bus time (mock+can only)
CAN_NUMBER_PARAMS = ("bitrate", "data_bitrate", "port", "hop_limit", "rx_queue_size")
CAN_FLAG_PARAMS = ("fd", "receive_own_messages", "local_loopback", "ignore_rx_error_frames", "preserve_timestamps")
I2C_PARAMS = ("timeout", "paced")   # mock+i2c only: timeout=S, the client's wait for the server's answer;
                                   # paced=true: the bus holds each data read until its data exists (a replay)
PARAMS: dict[str, tuple[str, ...]] = {
    "serial": SERIAL_PARAMS, "can": CAN_PARAMS, "i2c": I2C_PARAMS, "gpio": (), "pwm": (), "pca9685": (),
}
BAUDRATES = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)
PARITIES = ("N", "E", "O", "M", "S")
BYTESIZES = (5, 6, 7, 8)
STOPBITS = (1.0, 1.5, 2.0)

Fail = Callable[[str], Exception]


@dataclass(frozen=True)
class UrlParts:
    """An address split by ``parse_address``: ``serial_scheme`` is the X of ``serial+X://`` ("" otherwise)."""

    kind: str
    mock: bool
    serial_scheme: str
    body: str                 # everything between ``://`` and ``?``
    netloc: str               # the body up to its first ``/``
    path: str                 # the rest of the body, with its leading ``/``
    params: Mapping[str, str]


Parsed = tuple[str, str, tuple[int, ...]]   # backend, location, numbers


def typed_option(text: str) -> Any:
    """A query value as can.Bus wants it: true/false, an int (any base), a float, else the text."""
    lowered = text.lower()
    if lowered in ("true", "false"):
        return lowered == "true"
    try:
        return int(text, 0)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def number(text: str, what: str, fail: Fail) -> int:
    """*text* as an int (``0x40`` too), else *fail* naming *what*."""
    try:
        return int(text, 0)
    except ValueError:
        raise fail(f"{what} {text!r} is not a number") from None


def check_params(kind: str, params: Mapping[str, str], fail: Fail) -> None:
    """Every query parameter is one *kind* takes; an unknown one fails with a did-you-mean."""
    allowed = PARAMS[kind]
    for key in params:
        if key not in allowed:
            import difflib   # only for a misspelt option
            close = difflib.get_close_matches(key, allowed, n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            known = ", ".join(allowed) if allowed else "none"
            raise fail(f"unknown parameter '{key}'{hint}; {kind} addresses take: {known}")


def _check_serial_params(params: Mapping[str, str], fail: Fail) -> None:
    if "baud" in params:
        baud = number(params["baud"], "baud", fail)
        if baud not in BAUDRATES:
            raise fail(f"baud {baud} is not a serial rate; use one of {', '.join(map(str, BAUDRATES))}")
    if "bytesize" in params and number(params["bytesize"], "bytesize", fail) not in BYTESIZES:
        raise fail(f"bytesize {params['bytesize']} must be 5, 6, 7 or 8")
    if "parity" in params and params["parity"].upper() not in PARITIES:
        raise fail(f"parity {params['parity']!r} must be N, E, O, M or S")
    if "stopbits" in params:
        try:
            stop = float(params["stopbits"])
        except ValueError:
            stop = -1.0
        if stop not in STOPBITS:
            raise fail(f"stopbits {params['stopbits']!r} must be 1, 1.5 or 2")
    usb = params.get("usb")
    if usb is not None:
        vendor, sep, product = usb.partition(":")
        if not sep or not all(len(p) == 4 and all(c in "0123456789abcdefABCDEF" for c in p) for p in (vendor, product)):
            raise fail(f"usb={usb!r} must be VENDOR:PRODUCT in 4-digit hex as lsusb prints it, e.g. usb=1546:01a7")
    if "serial" in params and not params["serial"].strip():
        raise fail("serial= (the USB serial number) is empty")


def parse_serial(parts: UrlParts, fail: Fail) -> Parsed:
    """``serial:///dev/PATH`` (backend ``path``) or ``serial+X://...`` (backend X, location the pyserial URL).

    ``clock=stamped`` (the device sends stamped frames: a replay's device clock) is taken only by
    ``mock+serial`` addresses, so a real device can never set the time its driver sees.
    """
    _check_serial_params(parts.params, fail)
    if "clock" in parts.params:
        if not parts.mock:
            raise fail("clock= is only for mock+serial addresses (a replay's pty that sends stamped frames); "
                       "a real serial device is timed by its reader: remove clock=")
        if parts.params["clock"] not in SERIAL_CLOCKS:
            raise fail(f"clock={parts.params['clock']!r}: the one device clock is clock=stamped")
    if parts.serial_scheme:
        return parts.serial_scheme, f"{parts.serial_scheme}://{parts.body}", ()
    if parts.netloc or not parts.path.strip("/"):
        raise fail("a serial address is serial:// followed by an absolute device path (three slashes)")
    return "path", parts.path, ()


def parse_can(parts: UrlParts, fail: Fail) -> Parsed:
    """``can://INTERFACE/CHANNEL``: backend the python-can interface, location the channel.

    ``clock=stamped`` (frames keep their senders' stamps: a replay's device clock) is taken only by
    ``mock+can://udp_multicast`` addresses, so a real bus can never set the time its driver sees.
    """
    if not parts.netloc or not parts.path.strip("/"):
        raise fail("expected can://INTERFACE/CHANNEL")
    for key in CAN_NUMBER_PARAMS:
        if key in parts.params and not parts.params[key].isdigit():
            raise fail(f"{key}={parts.params[key]!r} must be a whole number")
    for key in CAN_FLAG_PARAMS:
        if key in parts.params and parts.params[key].lower() not in ("true", "false"):
            raise fail(f"{key}={parts.params[key]!r} must be true or false")
    if "clock" in parts.params:
        if not parts.mock or parts.netloc != "udp_multicast":
            raise fail("clock= is only for mock+can://udp_multicast addresses (a replay's bus that sends "
                       "recorded stamps); a real CAN bus is timed by its kernel: remove clock=")
        if parts.params["clock"] not in CAN_CLOCKS:
            raise fail(f"clock={parts.params['clock']!r}: the one device clock is clock=stamped")
    return parts.netloc, parts.path.strip("/"), ()


def _chip_address(text: str, fail: Fail) -> int:
    value = number(text, "I2C chip address", fail)
    if not 0x03 <= value <= 0x77:
        raise fail(f"I2C chip address {text} is not a 7-bit device address (0x03..0x77)")
    return value


def _channel(text: str, fail: Fail, limit: int | None = None) -> int:
    if not text.isdigit():
        raise fail(f"channel {text!r} is not a channel number")
    value = int(text)
    if limit is not None and value >= limit:
        raise fail(f"channel {value} is beyond the chip's {limit} channels (0..{limit - 1})")
    return value


def _split_last(path: str, count: int, what: str, fail: Fail) -> tuple[str, list[str]]:
    """``/a/b.sock/0x40/3`` with count 2 -> ("/a/b.sock", ["0x40", "3"])."""
    parts = path.rstrip("/").split("/")
    if len(parts) < count + 2 or not all(parts[-count:]):   # leading "" of an absolute path + location
        raise fail(f"expected {what}")
    return "/".join(parts[:-count]), parts[-count:]


def mock_i2c_timeout(text: str, fail: Fail) -> float:
    """``timeout=`` of a mock+i2c address: seconds, a finite number > 0, else *fail*."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise fail(f"timeout={text!r} must be a number of seconds > 0 (how long the client waits for the mock "
                   "I2C bus server's answer), e.g. timeout=60")
    return value


def parse_i2c(parts: UrlParts, fail: Fail) -> Parsed:
    """``i2c://BUS/CHIP`` and ``pca9685://BUS/CHIP/CHANNEL`` (mock: a bus socket path instead of BUS).

    ``timeout=S`` (how long the client waits for the server's answer; the mock client's default
    is 2 s) and ``paced=true`` (the bus holds each data read until its data exists, so a driver
    reads back to back instead of on its timer) are taken only by ``mock+i2c`` addresses: a
    replay's bus holds a data read until the player releases it (docs/replay.md), where a real
    adapter times out in its kernel driver and a real chip is read on the driver's timer.
    """
    kind = parts.kind
    if "timeout" in parts.params:
        if not parts.mock:
            raise fail("timeout= is only for mock+i2c addresses (how long the client waits for the mock bus "
                       "server); a real adapter's timeout is its kernel driver's: remove timeout=")
        mock_i2c_timeout(parts.params["timeout"], fail)
    if "paced" in parts.params:
        if not parts.mock:
            raise fail("paced= is only for mock+i2c addresses (a replay's bus, which holds each data read until "
                       "its data exists); a real chip is read on the driver's timer: remove paced=")
        if parts.params["paced"].lower() not in ("true", "false"):
            raise fail(f"paced={parts.params['paced']!r} must be true or false")
    count = 1 if kind == "i2c" else 2
    what = "BUS/CHIP" if kind == "i2c" else "BUS/CHIP/CHANNEL"
    if parts.mock:
        if parts.netloc:
            raise fail(f"a mock {kind} address is {MOCK_PREFIX}{kind}:///path/to/bus.sock/{what[4:]}")
        backend = "mock"
        location, tail = _split_last(parts.path, count, f"/path/to/bus.sock/{what[4:]}", fail)
    else:
        tail = parts.path.strip("/").split("/") if parts.path.strip("/") else []
        if not parts.netloc.isdigit() or len(tail) != count:
            raise fail(f"expected {kind}://{what} with BUS the adapter number (1 for /dev/i2c-1)")
        backend, location = "smbus", parts.netloc
    numbers: tuple[int, ...] = (_chip_address(tail[0], fail),)
    if kind == "pca9685":
        numbers += (_channel(tail[1], fail, 16),)
    return backend, location, numbers


def parse_gpio(parts: UrlParts, fail: Fail) -> Parsed:
    """``gpio://CHIP/LINE,LINE`` (CHIP under /dev; mock: the chip socket path)."""
    full = (f"/dev/{parts.netloc}" if parts.netloc else "") + parts.path
    chip, _, last = full.rstrip("/").rpartition("/")
    numbers: tuple[int, ...] = ()
    if last and all(p.strip().isdigit() for p in last.split(",")):
        numbers = tuple(int(p) for p in last.split(","))
        if len(set(numbers)) != len(numbers):
            raise fail(f"line list {last!r} repeats a line")
    elif last and "," in last:
        raise fail(f"line list {last!r} must be line numbers separated by commas")
    else:
        chip = full.rstrip("/")
    if not chip or chip == "/dev":
        raise fail("expected gpio://CHIP/LINE,LINE (CHIP as gpiodetect names it)")
    if parts.mock and parts.netloc:
        raise fail("a mock gpio address is mock+gpio:///path/to/chip.sock/LINES")
    return ("mock" if parts.mock else "gpiod"), chip, numbers


def parse_pwm(parts: UrlParts, fail: Fail) -> Parsed:
    """``pwm://pwmchipN/CHANNEL`` (under /sys/class/pwm; mock: any directory)."""
    full = (f"{SYSFS_PWM}/{parts.netloc}" if parts.netloc else "") + parts.path
    if parts.mock and parts.netloc:
        raise fail("a mock pwm address is mock+pwm:///path/to/chipdir/CHANNEL")
    location, tail = _split_last(full, 1, "CHIP/CHANNEL", fail)
    channel = _channel(tail[0], fail)
    if not parts.mock and not location.startswith(SYSFS_PWM + "/"):
        raise fail(f"a real pwm chip lives under {SYSFS_PWM}; a directory elsewhere is mock+pwm:///DIR/CHANNEL")
    return ("mock" if parts.mock else "sysfs"), location, (channel,)


PARSERS: dict[str, Callable[[UrlParts, Fail], Parsed]] = {
    "serial": parse_serial, "can": parse_can, "i2c": parse_i2c, "pca9685": parse_i2c, "gpio": parse_gpio,
    "pwm": parse_pwm,
}
