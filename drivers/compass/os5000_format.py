"""The OceanServer OS5000 compass's ``$C`` ASCII output: field table and parser.

From the OS5000 series manual (format type 0x01, the factory default of the OS5000-S,
-US and -T, 19200 baud 8N1): ``$C<heading>P<pitch>R<roll>T<temp>*<cc>`` CR LF, e.g.
``$C320.5P0.2R-18.3T19.0*3C``. Each value is preceded by its tag, so the parser does not
depend on which outputs are enabled (``<esc>X`` selects them); ``*cc`` is the NMEA-style
XOR of the characters between ``$`` and ``*`` in two hex digits.

The heading is magnetic unless a declination was entered into the compass itself (then
it is already true: set the driver's ``declination_deg = 0``). Pitch is positive nose up
and roll positive right side down (the aerospace convention the drivers publish in).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

from pynmeagps.nmeahelpers import calc_checksum

# tag -> (attribute of Os5000Reading, unit); the order is the order the manual lists them in
OS5000_FIELDS: dict[str, tuple[str, str]] = {
    "C": ("heading", "deg"),        # compass heading, corrected for the compass's own declination if set
    "P": ("pitch", "deg"),
    "R": ("roll", "deg"),
    "T": ("temperature", "degC"),   # board temperature: a crude relative measure
    "D": ("depth", "m"),            # OS5500-USG pressure sensor
    "Mx": ("mag_x", "mG"),          # calibrated magnetic field per sensor axis
    "My": ("mag_y", "mG"),
    "Mz": ("mag_z", "mG"),
    "Ax": ("accel_x", "g"),         # acceleration per sensor axis
    "Ay": ("accel_y", "g"),
    "Az": ("accel_z", "g"),
}
# the documented ranges (OS5000 series manual, specifications): heading 0..360, pitch +-90,
# roll +-180 (deg); operating temperature -40..85 C. A value outside is not a measurement.
OS5000_RANGES: dict[str, tuple[float, float]] = {
    "heading": (0.0, 360.0),
    "pitch": (-90.0, 90.0),
    "roll": (-180.0, 180.0),
    "temperature": (-40.0, 85.0),
}
OS5000_BAUDRATES = (4800, 9600, 14400, 19200, 38400, 57600, 115200)  # <esc>B 0..6
_LINE = re.compile(r"^\$(C[^*]*)\*([0-9A-Fa-f]{2})\s*$")
_FIELD = re.compile(r"([A-Z][a-z]?)([-+]?\d+(?:\.\d*)?|[-+]?\.\d+)")


class Os5000Error(ValueError):
    """A line that is not a valid ``$C`` sentence."""


class Os5000BadChecksum(Os5000Error):
    """The ``*cc`` checksum does not match the line."""


@dataclass(frozen=True)
class Os5000Reading:
    """One ``$C`` line. Degrees, degrees C, metres; None when the output is not enabled."""

    heading: float
    pitch: float | None = None
    roll: float | None = None
    temperature: float | None = None
    depth: float | None = None
    mag_x: float | None = None
    mag_y: float | None = None
    mag_z: float | None = None
    accel_x: float | None = None
    accel_y: float | None = None
    accel_z: float | None = None
    unknown: dict[str, float] = field(default_factory=dict)  # tags this table does not know


def is_os5000_line(line: bytes) -> bool:
    """True when *line* (after any leading noise) is a ``$C`` sentence rather than NMEA."""
    start = line.rfind(b"$")
    after = line[start + 2:start + 3]
    return start >= 0 and line[start + 1:start + 2] == b"C" and len(after) == 1 and after in b"0123456789+-."


def parse_os5000(line: bytes) -> tuple[Os5000Reading, int]:
    """The reading in *line* and the count of noise bytes before its ``$``.

    Raises Os5000BadChecksum for a wrong checksum and Os5000Error for anything else
    that is not a complete ``$C`` sentence with a heading.
    """
    start = line.rfind(b"$")
    if start < 0:
        raise Os5000Error(f"no '$' in {line[:40]!r}")
    try:
        text = line[start:].decode("ascii").rstrip("\r\n")
    except UnicodeDecodeError:
        raise Os5000Error(f"non-ASCII bytes in {line[start:start + 40]!r}") from None
    match = _LINE.match(text)
    if match is None:
        raise Os5000Error(f"not a $C...*cc sentence: {text[:60]!r}")
    body, given = match.group(1), match.group(2).upper()
    expected = calc_checksum(body)
    if given != expected:
        raise Os5000BadChecksum(f"checksum {given} should be {expected} in {text[:60]!r}")
    values: dict[str, float] = {}
    unknown: dict[str, float] = {}
    pos = 0
    for m in _FIELD.finditer(body):
        if m.start() != pos:
            raise Os5000Error(f"unreadable field at {body[pos:pos + 12]!r} in {text[:60]!r}")
        pos = m.end()
        tag, value = m.group(1), float(m.group(2))
        if not math.isfinite(value):
            raise Os5000Error(f"non-finite {tag} in {text[:60]!r}")
        if tag in OS5000_FIELDS:
            values[OS5000_FIELDS[tag][0]] = value
        else:
            unknown[tag] = value
    if pos != len(body):
        raise Os5000Error(f"unreadable field at {body[pos:pos + 12]!r} in {text[:60]!r}")
    if "heading" not in values:
        raise Os5000Error(f"no heading (C field) in {text[:60]!r}")
    return Os5000Reading(**values, unknown=unknown), start
