"""Device addresses: one URL per device, whose scheme picks the port kind and real or mock.

The grammar (docs/ports.md has the table)::

    serial:///dev/u2sa/gps?baud=9600              a device path; optional bytesize, parity, stopbits,
                                                   usb=VID:PID and serial=SERIALNO (the udev identity)
    serial+socket://host:7000?baud=9600           any pyserial URL after "serial+" (socket, rfc2217, loop, spy)
    can://socketcan/can0?bitrate=500000           python-can interface / channel; the other can.Bus options
                                                   an address may carry are listed in address_schemes.CAN_PARAMS
    i2c://1/0x68                                  adapter number (/dev/i2c-1) / 7-bit chip address
    gpio://gpiochip0/17,27                        /dev/gpiochip0, the lines the device uses (may be empty)
    pwm://pwmchip0/0                              /sys/class/pwm/pwmchip0, channel 0
    pca9685://1/0x40/3                            I2C adapter / chip address / channel 0..15

    mock+serial:///run/sim/gps?baud=9600          a pty (symlink) whose other end a mock device holds
                                                   (clock=stamped: it sends stamped frames, a replay's clock)
    mock+can://udp_multicast/239.74.163.2?port=17270   python-can across processes (also virtual, u2sa_unpluggable)
    mock+i2c:///run/sim/i2c-1.sock/0x68           the mock I2C bus server's Unix socket / chip address
                                                   (timeout=S: the client waits S s for an answer, default 2;
                                                   paced=true: the bus paces the data reads, a replay's)
    mock+gpio:///run/sim/gpiochip0.sock/5,6       the mock GPIO chip's Unix socket / lines
    mock+pwm:///run/sim/pwmchip0/0                a sysfs-shaped directory / channel
    mock+pca9685:///run/sim/i2c-1.sock/0x40/3     a PCA9685 model on the mock I2C bus

Replay feeds recorded I/O into mock devices, so a replayed device has a ``mock+`` address.

API (stable; ``u2sa check``, install and udev generation build on it):

- :func:`parse_address` ``(text, *, device) -> DeviceAddress``; :class:`AddressError` (a
  ``ValueError``) names the device, the bad text and the fix with an example.
- :class:`DeviceAddress`: ``url``, ``kind`` (:data:`KINDS`), ``mock``, ``params``, and typed
  properties per kind (``serial_path``, ``baud``..., ``can_interface``..., ``i2c_bus``,
  ``i2c_timeout``, ``i2c_paced``, ``chip_address``, ``gpio_chip``, ``lines``, ``pwm_chip``, ``pwm_channel``, ``output_id``,
  ``usb_id``...) and derived copies (``with_params``, ``with_chip_address``: another chip on the same bus).
- :func:`make_address` builds one from parts (used by the mocks and the install).

A query parameter the kind does not take is an error with a did-you-mean (``bitrat=`` is
not handed on). Each kind's parser and parameters are its grammar (``u2sa_hw/ports/<kind>/grammar.py``),
found through the kind table (:data:`u2sa_hw.ports.kinds.PORT_KINDS`); the pieces they share are
:mod:`u2sa_hw.ports.address_schemes`. Opening is :func:`u2sa_hw.ports.opener.open_port`;
neither module imports a port library.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Mapping
from urllib.parse import parse_qsl, quote, urlencode

from u2sa_hw.ports.address_schemes import MOCK_PREFIX, SYSFS_PWM, UrlParts, check_params, typed_option
from u2sa_hw.ports.kinds import PORT_KINDS

__all__ = ["KINDS", "MOCK_PREFIX", "EXAMPLES", "MOCK_EXAMPLES", "PARAMS", "SYSFS_PWM", "AddressError", "DeviceAddress",
           "parse_address", "make_address"]

KINDS = tuple(PORT_KINDS)   # the address kinds, one per line of the kind table
EXAMPLES = {name: kind.example for name, kind in PORT_KINDS.items()}
MOCK_EXAMPLES = {name: kind.mock_example for name, kind in PORT_KINDS.items()}
PARAMS = {name: kind.params for name, kind in PORT_KINDS.items()}   # the query parameters each kind takes


class AddressError(ValueError):
    """A device address that cannot be parsed; the text names the device, the address and the fix."""

    def __init__(self, device: str, text: str, problem: str, *, kind: str | None = None) -> None:
        self.device = device
        self.text = text
        self.problem = problem
        example = (f"{EXAMPLES[kind]} (mock: {MOCK_EXAMPLES[kind]})" if kind in EXAMPLES
                   else "; ".join(EXAMPLES.values()))
        self.fix = f"write it like {example}"
        super().__init__(f"device '{device}': address {text!r}: {problem}; {self.fix} (docs/ports.md)")


@dataclass(frozen=True)
class DeviceAddress:
    """A parsed device address.

    ``backend`` says what opens it: serial ``"path"`` or a pyserial URL scheme; CAN the
    python-can interface; I2C/PCA9685 ``"smbus"`` or ``"mock"``; GPIO ``"gpiod"`` or ``"mock"``;
    PWM ``"sysfs"`` or ``"mock"``. ``location`` is the path, channel, adapter number or socket
    path; ``numbers`` the chip address, lines or channel that follow it.
    """

    url: str
    kind: str
    mock: bool
    params: Mapping[str, str]
    backend: str
    location: str
    numbers: tuple[int, ...] = ()

    def __hash__(self) -> int:
        return hash(self.url)

    def __str__(self) -> str:
        return self.url

    @property
    def scheme(self) -> str:
        """The scheme as written, e.g. ``serial``, ``mock+can``, ``serial+socket``."""
        return self.url.split("://", 1)[0]

    def _need(self, *kinds: str) -> None:
        if self.kind not in kinds:
            raise AttributeError(f"a {self.kind} address has no such part (only {', '.join(kinds)} addresses do)")

    # ---- serial ------------------------------------------------------------------------------
    @property
    def serial_path(self) -> str:
        """The device path (``/dev/u2sa/gps``), or the pyserial URL for ``serial+X://`` forms."""
        self._need("serial")
        return self.location

    @property
    def is_serial_url(self) -> bool:
        """True for ``serial+X://`` addresses opened with pyserial's serial_for_url."""
        self._need("serial")
        return self.backend != "path"

    @property
    def baud(self) -> int:
        """Bit rate (default 9600)."""
        self._need("serial")
        return int(self.params.get("baud", "9600"))

    @property
    def bytesize(self) -> int:
        """Data bits (default 8)."""
        self._need("serial")
        return int(self.params.get("bytesize", "8"))

    @property
    def parity(self) -> str:
        """Parity letter N/E/O/M/S (default N)."""
        self._need("serial")
        return self.params.get("parity", "N").upper()

    @property
    def stopbits(self) -> float:
        """Stop bits 1, 1.5 or 2 (default 1)."""
        self._need("serial")
        return float(self.params.get("stopbits", "1"))

    @property
    def framing(self) -> str:
        """``8N1``-style framing."""
        return f"{self.bytesize}{self.parity}{self.stopbits:g}"

    @property
    def device_clock(self) -> bool:
        """True for ``mock+serial://...?clock=stamped``: the pty carries stamped frames (a replay's device
        clock, :mod:`u2sa_hw.ports.serial.clock`); never for a real address (the parser refuses it)."""
        self._need("serial")
        return self.mock and self.params.get("clock") == "stamped"

    @property
    def usb_id(self) -> tuple[str, str] | None:
        """``(vendor, product)`` in 4-digit lower-case hex from ``usb=VID:PID``, or None."""
        self._need("serial")
        text = self.params.get("usb")
        if not text:
            return None
        vendor, _, product = text.lower().partition(":")
        return vendor, product

    @property
    def usb_serial(self) -> str | None:
        """The USB serial number from ``serial=...``, or None."""
        self._need("serial")
        return self.params.get("serial") or None

    # ---- CAN ---------------------------------------------------------------------------------
    @property
    def can_interface(self) -> str:
        """The python-can interface (``socketcan``, ``virtual``, ``udp_multicast``...)."""
        self._need("can")
        return self.backend

    @property
    def can_channel(self) -> str:
        """The python-can channel (``can0``, a virtual bus name, a multicast group)."""
        self._need("can")
        return self.location

    @property
    def bitrate(self) -> int | None:
        """``bitrate=`` in bit/s, or None (leave the interface as configured)."""
        self._need("can")
        text = self.params.get("bitrate")
        return int(text) if text and int(text) > 0 else None

    @property
    def udp_port(self) -> int | None:
        """``port=`` of a udp_multicast bus, or None (python-can's default)."""
        self._need("can")
        text = self.params.get("port")
        return int(text) if text and int(text) > 0 else None

    @property
    def bus_options(self) -> dict[str, Any]:
        """Every parameter except ``bitrate``, typed, for ``can.Bus``."""
        self._need("can")
        return {k: typed_option(v) for k, v in self.params.items() if k != "bitrate"}

    # ---- I2C and PCA9685 ---------------------------------------------------------------------
    @property
    def i2c_bus(self) -> int | str:
        """The adapter number (1 -> /dev/i2c-1), or for mocks ``"mock:/path/to/bus.sock"``."""
        self._need("i2c", "pca9685")
        return f"mock:{self.location}" if self.mock else int(self.location)

    @property
    def i2c_timeout(self) -> float | None:
        """``timeout=`` of a ``mock+i2c`` address: seconds the client waits for the mock bus server's
        answer, or None (the client's default, 2 s); real addresses never carry it (the parser refuses it)."""
        self._need("i2c", "pca9685")
        text = self.params.get("timeout")
        return float(text) if text is not None else None

    @property
    def i2c_paced(self) -> bool:
        """``paced=true`` of a ``mock+i2c`` address: the bus holds each data read until its data exists (a
        replay, docs/replay.md), so the driver reads back to back rather than on its timer."""
        self._need("i2c", "pca9685")
        return self.params.get("paced", "false").lower() == "true"

    @property
    def chip_address(self) -> int:
        """The chip's 7-bit I2C address."""
        self._need("i2c", "pca9685")
        return self.numbers[0]

    # ---- GPIO --------------------------------------------------------------------------------
    @property
    def gpio_chip(self) -> str:
        """``/dev/gpiochipN``, or for mocks ``"mock:/path/to/chip.sock"``."""
        self._need("gpio")
        return f"mock:{self.location}" if self.mock else self.location

    @property
    def lines(self) -> tuple[int, ...]:
        """The line offsets the device uses (empty: not listed)."""
        self._need("gpio")
        return self.numbers

    # ---- PWM ---------------------------------------------------------------------------------
    @property
    def pwm_chip(self) -> str:
        """The sysfs chip directory (``/sys/class/pwm/pwmchip0`` or a mock directory)."""
        self._need("pwm")
        return self.location

    @property
    def pwm_channel(self) -> int:
        """The PWM channel (sysfs ``pwmN``, PCA9685 output 0..15)."""
        self._need("pwm", "pca9685")
        return self.numbers[-1]

    @property
    def output_id(self) -> tuple[Any, ...]:
        """What makes two PWM addresses one output pin (sysfs chip + channel; PCA9685 bus + chip + channel),
        however the chip address is spelt: sysfs and a PCA9685 let two writers share a pin unnoticed."""
        self._need("pwm", "pca9685")
        return (self.kind, self.mock, self.location, *self.numbers)

    @property
    def shared_frame_id(self) -> tuple[Any, ...] | None:
        """The chip whose outputs share one frame period (a PCA9685's prescaler), or None (sysfs channels)."""
        self._need("pwm", "pca9685")
        return (self.kind, self.mock, self.location, self.numbers[0]) if self.kind == "pca9685" else None

    # ---- derived forms -----------------------------------------------------------------------
    def with_params(self, **changes: Any) -> DeviceAddress:
        """A copy with query parameters set (None removes one), e.g. another baud."""
        params = dict(self.params)
        for key, value in changes.items():
            if value is None:
                params.pop(key, None)
            else:
                params[key] = str(value)
        return make_address(self.kind, self.location, self.numbers, params=params, mock=self.mock,
                            backend=self.backend, device="(derived)")

    def with_chip_address(self, chip: int) -> DeviceAddress:
        """The same bus (adapter, mock or replay socket, parameters) with another 7-bit chip address, e.g.
        an MPU-9250's AK8963 at 0x0c beside ``i2c://1/0x68``; AddressError outside 0x03..0x77."""
        self._need("i2c", "pca9685")
        return make_address(self.kind, self.location, (chip, *self.numbers[1:]), params=self.params,
                            mock=self.mock, backend=self.backend, device="(derived)")


def parse_address(text: str, *, device: str) -> DeviceAddress:
    """Parse device *device*'s address *text*; AddressError (one line, with the fix) when it is wrong."""
    if not isinstance(text, str):
        raise AddressError(device, repr(text), f"an address is a string, not {type(text).__name__}")
    url = text.strip()
    scheme, sep, rest = url.partition("://")
    if not sep:
        guess = "serial" if url.startswith("/dev/") else "pwm" if url.startswith(SYSFS_PWM) else None
        if url.startswith("pca9685:"):
            guess = "pca9685"
        meant = {"serial": f" (did you mean 'serial://{url}'?)",
                 "pwm": f" (did you mean 'pwm://{url[len(SYSFS_PWM) + 1:]}/CHANNEL'?)"}.get(guess or "", "")
        raise AddressError(device, text, f"not a URL (no scheme://){meant}", kind=guess)
    mock = scheme.startswith(MOCK_PREFIX)
    base = scheme[len(MOCK_PREFIX):] if mock else scheme
    kind, plus, serial_scheme = base.partition("+")
    if kind not in KINDS:
        import difflib   # only for a misspelt scheme
        close = difflib.get_close_matches(base, [*KINDS, *(MOCK_PREFIX + k for k in KINDS)], n=1)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        raise AddressError(device, text, f"unknown scheme '{scheme}'{hint}; known: "
                           f"{', '.join(KINDS)}, their mock+ forms and serial+<pyserial scheme>")
    kind_hint = kind

    def fail(problem: str) -> AddressError:
        return AddressError(device, text, problem, kind=kind_hint)

    if plus and (kind != "serial" or mock or not serial_scheme):
        raise fail(f"'{scheme}': only serial takes a pyserial scheme after '+' (serial+socket://host:port)")
    body, _, query = rest.partition("?")
    try:
        params = dict(parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query)))
    except ValueError:
        raise fail(f"bad query string {query!r} (use key=value&key=value)") from None
    port_kind = PORT_KINDS[kind]
    check_params(kind, port_kind.params, params, fail)
    netloc, slash, path = body.partition("/")
    parts = UrlParts(kind=kind, mock=mock, serial_scheme=serial_scheme if plus else "", body=body, netloc=netloc,
                     path=slash + path, params=params)
    backend, location, numbers = port_kind.parse(parts, fail)
    return DeviceAddress(url=url, kind=kind, mock=mock, params=MappingProxyType(params), backend=backend,
                         location=location, numbers=numbers)


def make_address(kind: str, location: str, numbers: tuple[int, ...] | list[int] = (), *,
                 params: Mapping[str, Any] | None = None, mock: bool = False, backend: str | None = None,
                 device: str = "(built)") -> DeviceAddress:
    """Build (and check) an address from parts: the inverse of the fields ``parse_address`` fills.

    *location* is what the kind's ``location`` holds: a device path or pyserial URL, a CAN
    channel (with *backend* the interface), an I2C adapter number or mock socket path, a
    GPIO chip path or mock socket path, a PWM chip directory. A kind not named below (a new
    one in the kind table) is written ``KIND://LOCATION/N/...`` and parsed by its own grammar.
    """
    prefix = MOCK_PREFIX if mock else ""
    query = urlencode({k: str(v) for k, v in (params or {}).items()}, safe=":/")
    suffix = f"?{query}" if query else ""
    nums = list(numbers)
    if kind == "serial":
        if backend and backend != "path":
            rest = location.split("://", 1)[1] if "://" in location else location
            url = f"serial+{backend}://{rest}"
        else:
            url = f"{prefix}serial://{quote(location, safe='/:@')}"
    elif kind == "can":
        url = f"{prefix}can://{backend or 'socketcan'}/{location}"
    elif kind == "i2c":
        url = f"{prefix}i2c://{'' if mock else location}{location if mock else ''}/0x{nums[0]:02x}"
    elif kind == "pca9685":
        url = f"{prefix}pca9685://{'' if mock else location}{location if mock else ''}/0x{nums[0]:02x}/{nums[1]}"
    elif kind == "gpio":
        chip = location
        if not mock and chip.startswith("/dev/") and chip.count("/") == 2:
            where = chip[len("/dev/"):]
        else:
            where = chip if chip.startswith("/") else f"/{chip}"
        lines = ",".join(str(n) for n in nums)
        url = f"{prefix}gpio://{where}" + (f"/{lines}" if lines else "")
    elif kind == "pwm":
        where = location[len(SYSFS_PWM) + 1:] if not mock and location.startswith(SYSFS_PWM + "/") else location
        url = f"{prefix}pwm://{where}/{nums[0]}"
    elif kind in KINDS:   # any other kind: KIND://LOCATION/N/... (a new kind whose grammar reads that form)
        url = f"{prefix}{kind}://{location}" + "".join(f"/{n}" for n in nums)
    else:
        raise AddressError(device, location, f"unknown kind {kind!r}")
    return parse_address(url + suffix, device=device)
