"""The NMEA 0183 sentences a compass or attitude sensor sends: field tables, parsing, ranges.

Each checksum-valid line becomes one :class:`CompassPart` -- what that one sentence says
(a heading with its reference, pitch, roll, rate of turn, accuracies) -- or None when it
is no compass sentence. Fields are read here rather than by pynmeagps because half of
the sentences are proprietary and because every number must be bounded before use: a
field is a plain decimal (no exponent, no ``inf``/``nan``, at most 24 characters) and each
value is checked against its physical range and the configured device range
(:class:`AttitudeLimits`); a value outside is dropped and counted per kind
(:class:`~u2sa_hw.drivers.value_ranges.ValueDrops`), the rest of the sentence is still used.
A value the sentence itself marks not valid (a status letter) is dropped and counted in
the second counter (``not_valid``).

- ``--HDG,h,d,E/W,v,E/W``: sensor heading, deviation, variation (reference "sensor");
- ``--HDM,h,M``: magnetic heading; ``--HDT,h,T``: true heading;
- ``--THS,h,m``: true heading; mode A (autonomous) and E (estimated, dead reckoning) are
  used, M (manual), S (simulator) and V (not valid) dropped;
- ``--ROT,r,A``: rate of turn, deg/min, negative = bow to port; status V dropped;
- ``--XDR,A,x,D,NAME,...``: angle transducers in degrees, PITCH/PTCH/TRIM -> pitch,
  ROLL/HEEL -> roll;
- ``PASHR,t,h,T,r,p,heave,sr,sp,sh,q,i`` (OxTS, Hemisphere, NovAtel): true heading, roll,
  pitch and their 1-sigma accuracies;
- ``PTNTHTM,h,s,p,s,r,s,dip,b`` / ``PTNTHPR,h,s,p,s,r,s`` (TNT Revolution, Honeywell
  HMR3000): heading (reference "device": the compass applies its own deviation and
  variation), pitch, roll with status letters; an alarm letter (L, P, C, V) drops its
  value, and any alarm drops the heading.

Signs: pitch positive nose (bow) up, roll positive right (starboard) side down, so a trim
reading is a pitch and a heel reading a roll.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from u2sa_hw.drivers.nmea_fields import MalformedSentence, checked_body, is_foreign, sentence_text
from u2sa_hw.drivers.value_ranges import ValueDrops

HEADING_DEG = (-360.0, 360.0)       # a direction; devices send 0..360 (a few -180..180)
DEVIATION_DEG = (-180.0, 180.0)      # HDG deviation and variation, after the E/W sign
ROT_DEG_MIN = (-9999.9, 9999.9)      # ROT's own format: up to four digits and one decimal
ACCURACY_DEG = (1e-6, 180.0)         # PASHR 1-sigma accuracies
PITCH_IDS = frozenset({"PITCH", "PTCH", "TRIM"})
ROLL_IDS = frozenset({"ROLL", "HEEL"})
THS_USED = frozenset({"A", "E"})
TNT_ALARMS = frozenset({"L", "P", "C", "V"})  # low/high alarm, tuning, voltage: the value is not valid
NMEA_KINDS = frozenset({"HDG", "HDM", "HDT", "THS", "ROT", "XDR"})
PROPRIETARY = frozenset({"PASHR", "PTNTHTM", "PTNTHPR"})
_NUMBER = re.compile(r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)")
MAX_NUMBER_CHARS = 24


@dataclass(frozen=True)
class AttitudeLimits:
    """The device's documented pitch and roll ranges (degrees, symmetric about 0)."""

    pitch_deg: float = 90.0
    roll_deg: float = 180.0


@dataclass(frozen=True)
class CompassPart:
    """What one sentence says, in degrees (None: not sent, or dropped)."""

    kind: str                          # HDG, HDM, HDT, THS, ROT, XDR, PASHR, PTNTHTM, PTNTHPR
    signature: str                     # the kind; XDR with its transducer names (bursts group by it)
    heading: float | None = None
    reference: str = ""                # "true", "magnetic", "sensor" (HDG) or "device" (PTNT)
    deviation: float | None = None     # HDG, east positive
    variation: float | None = None     # HDG, east positive
    pitch: float | None = None
    roll: float | None = None
    rate_deg_min: float | None = None  # ROT
    heading_sigma: float | None = None  # PASHR accuracies
    pitch_sigma: float | None = None
    roll_sigma: float | None = None
    mode: str = ""                     # THS mode letter
    noise_bytes: int = 0


class _Fields:
    """The comma-separated fields of one sentence, read as bounded numbers."""

    def __init__(self, kind: str, body: str, drops: ValueDrops, not_valid: ValueDrops) -> None:
        self.kind = kind
        self.values = body.split(",")
        self.drops = drops
        self.not_valid = not_valid

    def text(self, index: int) -> str:
        return self.values[index].strip().upper() if index < len(self.values) else ""

    def number(self, index: int, what: str) -> float | None:
        raw = self.values[index].strip() if index < len(self.values) else ""
        if not raw:
            return None
        if len(raw) > MAX_NUMBER_CHARS or _NUMBER.fullmatch(raw) is None:
            raise MalformedSentence(f"{self.kind}: {what} {raw[:30]!r} is not a decimal number", kind=self.kind)
        return float(raw)

    def ranged(self, index: int, what: str, bounds: tuple[float, float]) -> float | None:
        return self.drops.check(what, self.number(index, what), *bounds, unit=" deg")

    def flagged(self, value: float | None, status: str, bad: frozenset[str] | None, *, what: str,
                good: frozenset[str] | None = None) -> float | None:
        """*value* unless its status letter says it is not valid (then counted under *what*)."""
        invalid = (bad is not None and status in bad) or (good is not None and status not in good)
        if value is None or not invalid:
            return value
        self.not_valid.drop(f"{what} {status or 'empty'}", f"{self.kind} marks it {status or 'empty'}")
        return None


def _signed(value: float | None, letter: str) -> float | None:
    return None if value is None else (-abs(value) if letter == "W" else value)


def parse_compass_line(line: bytes, *, limits: AttitudeLimits, drops: ValueDrops,
                       not_valid: ValueDrops) -> CompassPart | None:
    """The :class:`CompassPart` of one line; None for a valid sentence that is no compass sentence, and
    for a line that is no error but no sentence for this driver (blank, or AIS ``!AIVDM``: the GPS
    driver's rule, :func:`~u2sa_hw.drivers.nmea_fields.is_foreign`).

    Raises :class:`~u2sa_hw.drivers.nmea_fields.BadChecksum` or ``MalformedSentence``; never anything else.
    """
    if is_foreign(line):
        return None
    text, noise = sentence_text(line)
    body = checked_body(text)
    address = body.split(",", 1)[0]
    if address in PROPRIETARY:
        kind = address
    elif len(address) == 5 and address[:2].isalpha() and address[2:] in NMEA_KINDS:
        kind = address[2:]
    else:
        return None
    f = _Fields(kind, body, drops, not_valid)
    pitch_range = (-min(limits.pitch_deg, 90.0), min(limits.pitch_deg, 90.0))
    roll_range = (-min(limits.roll_deg, 180.0), min(limits.roll_deg, 180.0))
    if kind == "HDG":
        return CompassPart(kind, kind, heading=f.ranged(1, "heading", HEADING_DEG), reference="sensor",
                           deviation=_signed(f.ranged(2, "deviation", DEVIATION_DEG), f.text(3)),
                           variation=_signed(f.ranged(4, "variation", DEVIATION_DEG), f.text(5)),
                           noise_bytes=noise)
    if kind in ("HDM", "HDT"):
        return CompassPart(kind, kind, heading=f.ranged(1, "heading", HEADING_DEG),
                           reference="magnetic" if kind == "HDM" else "true", noise_bytes=noise)
    if kind == "THS":
        mode = f.text(2)
        heading = f.flagged(f.ranged(1, "heading", HEADING_DEG), mode, None, what="THS mode", good=THS_USED)
        return CompassPart(kind, kind, heading=heading, reference="true", mode=mode, noise_bytes=noise)
    if kind == "ROT":
        rate = f.flagged(f.ranged(1, "rate of turn", ROT_DEG_MIN), f.text(2), frozenset({"V"}), what="ROT status")
        return CompassPart(kind, kind, rate_deg_min=rate, noise_bytes=noise)
    if kind == "XDR":
        return _xdr(f, pitch_range, roll_range, noise)
    if kind == "PASHR":
        if f.text(3) != "T":
            return None  # Ashtech's PASHR,POS/SAT/... share the address: not attitude
        return CompassPart(kind, kind, heading=f.ranged(2, "heading", HEADING_DEG), reference="true",
                           roll=f.ranged(4, "roll", roll_range), pitch=f.ranged(5, "pitch", pitch_range),
                           roll_sigma=f.ranged(7, "roll accuracy", ACCURACY_DEG),
                           pitch_sigma=f.ranged(8, "pitch accuracy", ACCURACY_DEG),
                           heading_sigma=f.ranged(9, "heading accuracy", ACCURACY_DEG), noise_bytes=noise)
    # PTNTHTM / PTNTHPR: heading, mag status, pitch, pitch status, roll, roll status[, dip, field]
    statuses = [f.text(2), f.text(4), f.text(6)]
    heading = f.ranged(1, "heading", HEADING_DEG)
    if heading is not None and any(s in TNT_ALARMS for s in statuses):
        alarm = next(s for s in statuses if s in TNT_ALARMS)
        heading = f.flagged(heading, alarm, TNT_ALARMS, what=f"{kind} heading alarm")
    return CompassPart(kind, kind, heading=heading, reference="device",
                       pitch=f.flagged(f.ranged(3, "pitch", pitch_range), statuses[1], TNT_ALARMS,
                                       what=f"{kind} pitch alarm"),
                       roll=f.flagged(f.ranged(5, "roll", roll_range), statuses[2], TNT_ALARMS,
                                      what=f"{kind} roll alarm"),
                       noise_bytes=noise)


def _xdr(f: _Fields, pitch_range: tuple[float, float], roll_range: tuple[float, float], noise: int) -> CompassPart:
    """Angle transducers (type A, degrees) named as pitch or roll; others only name the signature."""
    pitch = roll = None
    names = []
    for start in range(1, len(f.values) - 3, 4):
        kind, unit, name = f.text(start), f.text(start + 2), f.text(start + 3)
        names.append(name)
        if kind != "A" or unit not in ("D", "") or (name not in PITCH_IDS and name not in ROLL_IDS):
            continue
        if name in PITCH_IDS:
            pitch = f.ranged(start + 1, "pitch", pitch_range)
        else:
            roll = f.ranged(start + 1, "roll", roll_range)
    return CompassPart("XDR", "XDR:" + ",".join(sorted(names)), pitch=pitch, roll=roll, noise_bytes=noise)
