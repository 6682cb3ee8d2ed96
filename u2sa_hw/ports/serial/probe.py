"""The serial kind's probe (``u2sa check --probe``): what the port says, at which baud.

The port is read for a few seconds; the bytes are split into lines and each line is judged:
NMEA 0183 (``$``/``!`` talker sentence with ``*hh``), OceanServer OS5000 (``$C...*hh``),
with the XOR checksum checked, or garbage. A stream with few line ends and many
non-printable bytes is binary (a receiver in UBX or SiRF mode). When the configured baud
sees garbage the other common bauds are tried (a few seconds divided among them) and the
first with good checksums is named, as gpsd's ``gpsctl`` does. A pty ignores the baud rate:
against a mock the report still tells garbage from good sentences.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Mapping

if TYPE_CHECKING:
    from u2sa_hw.check.targets import Target
    from u2sa_hw.ports.address import DeviceAddress

PROBE = "serial"          # the probe's name (a target's ``port``)

COMMON_BAUDS = (4800, 9600, 19200, 38400, 57600, 115200)
GOOD_SHARE = 0.8           # this share of good checksums: the port works
_SENTENCE = re.compile(rb"^[$!]([A-Z0-9]{1,12}[^*]*)\*([0-9A-Fa-f]{2})\s*$")


@dataclass(frozen=True)
class StreamReport:
    """What a window of serial bytes held."""

    seconds: float
    nbytes: int
    nmea_good: int = 0
    nmea_bad: int = 0
    os5000_good: int = 0
    os5000_bad: int = 0
    other_lines: int = 0
    binary: bool = False

    @property
    def sentences(self) -> int:
        """Lines that look like sentences (good or bad checksum)."""
        return self.nmea_good + self.nmea_bad + self.os5000_good + self.os5000_bad

    @property
    def lines(self) -> int:
        """Every line seen."""
        return self.sentences + self.other_lines

    @property
    def good_share(self) -> float:
        """Share of lines with a good checksum (0 without lines)."""
        return (self.nmea_good + self.os5000_good) / self.lines if self.lines else 0.0

    @property
    def protocol(self) -> str:
        """``NMEA``, ``OS5000``, ``binary``, ``garbage`` or ``silent``."""
        if self.nbytes == 0:
            return "silent"
        os5000, nmea = self.os5000_good + self.os5000_bad, self.nmea_good + self.nmea_bad
        if max(os5000, nmea) * 2 >= self.lines > 0:   # most lines are sentences, good checksums or not
            return "OS5000" if os5000 > nmea else "NMEA"
        return "binary" if self.binary else "garbage"

    @property
    def works(self) -> bool:
        """True when most lines carry good checksums."""
        return self.lines > 0 and self.good_share >= GOOD_SHARE

    def text(self) -> str:
        """``NMEA, 12.0 lines/s, 100% good checksums (60 of 60)``."""
        rate = self.lines / self.seconds if self.seconds > 0 else 0.0
        if self.protocol == "silent":
            return f"silent for {self.seconds:.1f} s (no bytes)"
        if self.protocol in ("binary", "garbage") and not self.sentences:
            return f"{self.protocol}: {self.nbytes} bytes in {self.seconds:.1f} s, no sentence"
        good = self.nmea_good + self.os5000_good
        return (f"{self.protocol}, {rate:.1f} lines/s, {100 * self.good_share:.0f}% good checksums "
                f"({good} of {self.lines} lines)")


def xor_checksum(body: bytes) -> int:
    """The NMEA XOR of the bytes between ``$`` and ``*``."""
    value = 0
    for byte in body:
        value ^= byte
    return value


def judge(data: bytes, *, seconds: float) -> StreamReport:
    """Split *data* into lines and count good and bad sentences of each protocol."""
    counts = {"nmea_good": 0, "nmea_bad": 0, "os5000_good": 0, "os5000_bad": 0, "other_lines": 0}
    lines = data.split(b"\n")
    for raw in lines[1:-1] if len(lines) > 2 else lines[:-1]:   # the first and last may be cut
        line = raw.strip(b"\r")
        if not line:
            continue
        found = _SENTENCE.match(line)
        if not found:
            counts["other_lines"] += 1
            continue
        ok = xor_checksum(found.group(1)) == int(found.group(2), 16)
        family = "os5000" if found.group(1)[:1] == b"C" and not found.group(1)[:2].isalpha() else "nmea"
        counts[f"{family}_{'good' if ok else 'bad'}"] += 1
    printable = sum(1 for b in data if 32 <= b < 127 or b in (9, 10, 13))
    binary = bool(data) and (printable / len(data) < 0.7) and data.count(b"\n") < len(data) / 200
    return StreamReport(seconds=seconds, nbytes=len(data), binary=binary, **counts)


def read_window(port: Any, seconds: float) -> bytes:
    """Every byte *port* (anything with ``read(size)``) gives in *seconds*."""
    data = bytearray()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        chunk = port.read(4096)
        if chunk:
            data += chunk
    return bytes(data)


def _window_at(open_at: Callable[[int], Any], baud: int, seconds: float) -> StreamReport:
    port = open_at(baud)
    try:
        return judge(read_window(port, seconds), seconds=seconds)
    finally:
        port.close()


def probe_serial_port(open_at: Callable[[int], Any], *, baud: int, seconds: float) -> tuple[bool, str]:
    """Read the port *open_at(baud)* opens for *seconds*; on garbage try the other bauds. ``(ok, one-line text)``.

    The port is opened afresh at each baud (pyserial drops what arrived before the open).
    """
    first = _window_at(open_at, baud, seconds)
    text = f"{baud} baud: {first.text()}"
    if first.works or first.protocol == "silent":
        return first.works, text + ("" if first.works else "; check the wiring and that the device is powered")
    others = [b for b in COMMON_BAUDS if b != baud]
    each = max(0.5, seconds / len(others))
    for other in others:
        report = _window_at(open_at, other, each)
        if report.works:
            return False, f"{text}; at {other} baud: {report.text()}: set baud={other} in the address"
    return False, f"{text}; no other common baud ({', '.join(map(str, others))}) gives good sentences either"


def target_params(address: DeviceAddress, expect: Mapping[str, Any]) -> dict[str, Any]:
    """What the probe opens a serial *address* with, and the protocol the driver expects there."""
    return {"path": address.serial_path, "baud": address.baud, "protocol": expect.get("protocol")}


def probe(target: Target, seconds: float) -> tuple[bool, str, dict[str, Any]]:
    """Read the port for *seconds* at the configured baud (then the other common ones): lines, protocol,
    checksums; a protocol other than the driver's is a failure."""
    from u2sa_hw.ports import open_serial   # the package attribute: a test puts a fake UART there

    baud = int(target.params.get("baud", 9600))
    path = str(target.params["path"])
    ok, text = probe_serial_port(lambda rate: open_serial(path, device=target.name, baudrate=rate, timeout=0.1),
                                 baud=baud, seconds=seconds)
    expect = target.params.get("protocol")
    if ok and expect and expect.upper() not in text:
        return False, f"{text}; the driver expects {expect} (from its service's config)", {}
    return ok, text, {}
