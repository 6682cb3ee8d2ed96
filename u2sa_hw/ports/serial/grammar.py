"""The serial address grammar: ``serial:///dev/PATH``, ``serial+X://...`` (a pyserial URL), ``mock+serial:///PTY``.

The framing table here (:data:`BAUDRATES`, :data:`PARITIES`, :data:`BYTESIZES`, :data:`STOPBITS`) is the one
table of serial framing: the drivers' and the probe's choices come from it.
"""

from __future__ import annotations

from typing import Mapping

from u2sa_hw.ports.address_schemes import Fail, Parsed, UrlParts, number

SERIAL_PARAMS = ("baud", "bytesize", "parity", "stopbits", "usb", "serial", "clock")
SERIAL_CLOCKS = ("stamped",)   # clock=stamped: a replay's pty writes stamped frames (mock+serial only)
BAUDRATES = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)
PARITIES = ("N", "E", "O", "M", "S")
BYTESIZES = (5, 6, 7, 8)
STOPBITS = (1.0, 1.5, 2.0)


def check_serial_params(params: Mapping[str, str], fail: Fail) -> None:
    """The values of a serial address's framing and USB identity parameters are ones they may take, else *fail*."""
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
    check_serial_params(parts.params, fail)
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
