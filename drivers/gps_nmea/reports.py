"""What one position sentence (GGA, GNS, RMC, GLL) says: its fix status, position and quality.

Each sentence is read on its own into a :class:`PositionReport`, every value checked
against its physical range (``u2sa_hw.drivers.gps_nmea.limits``; an impossible value is left out and
its kind added to ``rejects``). ``u2sa_hw.drivers.gps_nmea.fix`` then merges the reports of one epoch.

The status of a report follows the sentence's own indicators:

- GGA quality 1-5 (GPS, DGPS, PPS, RTK fixed, RTK float) is ``gnss``, unless it counts
  fewer than 3 satellites in use (gpsd's rule). An empty count is *unknown*, not zero: the
  quality decides (some receivers never fill the field; gpsd reads it as 0, no fix). A
  count outside its range is no fix (fail safe). 6 is ``dr`` (dead reckoning), 7
  ``manual``, 8 ``simulator``, 0 or anything else ``none``.
- GNS: a mode letter per constellation; any of A, D, P, R, F is ``gnss`` (again unless
  it counts fewer than 3 satellites), else E ``dr``, S ``simulator``, M ``manual``, else ``none``.
- RMC and GLL: mode indicator E is ``dr``, S ``simulator``, M ``manual``, N ``none``;
  otherwise status A with a mode of A, D, P, R, F or none (NMEA before 2.3) is ``gnss``;
  status V, or a mode letter not defined for a fix (Quectel's C caution, U unsafe), is
  ``none``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from u2sa_hw.drivers.gps_nmea import limits as lim
from u2sa_hw.drivers.nmea_fields import Sentence, number, text

POSITION_KINDS = ("GGA", "GNS", "RMC", "GLL")    # in the order of preference for the same content
GGA_STATUS = {1: "gnss", 2: "gnss", 3: "gnss", 4: "gnss", 5: "gnss", 6: "dr", 7: "manual", 8: "simulator"}
FIX_MODES = frozenset("ADPRF")
MODE_STATUS = {"E": "dr", "S": "simulator", "M": "manual", "N": "none"}
MIN_SATELLITES = 3            # fewer in use: no fix (gpsd); an empty count is unknown, not 0
MIN_SATELLITES_3D = 4
# where the latitude field is among each sentence's fields (longitude two further on)
_LAT_FIELD = {"GGA": 1, "GNS": 1, "RMC": 2, "GLL": 0}


@dataclass
class PositionReport:
    """One position sentence's reading; absent or impossible values are None."""

    kind: str
    talker: str
    status: str = "none"               # gnss, dr, simulator, manual, none
    quality: int | None = None         # GGA quality
    lat: float | None = None
    lon: float | None = None
    decimals: int = 0                  # decimal places of the latitude minutes as sent
    alt_msl: float | None = None
    geoid_sep: float | None = None
    satellites: int | None = None
    hdop: float | None = None
    rejects: list[str] = field(default_factory=list)

    @property
    def is_fix(self) -> bool:
        """A GNSS fix with a usable position."""
        return self.status == "gnss" and self.lat is not None and self.lon is not None

    def richness(self) -> tuple[int, int, int]:
        """Sort key among reports of one epoch: an altitude, more satellites, the preferred kind."""
        return (self.alt_msl is not None, self.satellites if self.satellites is not None else -1,
                -POSITION_KINDS.index(self.kind))


def num(msg: object, name: str, kind: str, rejects: list[str]) -> float | None:
    """Field *name* as a finite float (:func:`number`); a number that is not finite or overflows a
    float (``inf``, a 400-digit field) is an impossible value: None, with *kind* added to *rejects*."""
    value = number(msg, name)
    if value is None:
        raw = getattr(msg, name, None)
        if isinstance(raw, (int, float)) and not isinstance(raw, bool):
            rejects.append(kind)
    return value


def checked(value: float | None, limit: lim.Limit, kind: str, rejects: list[str], *,
            open_low: bool = False) -> float | None:
    """*value* when within *limit*; None otherwise, with *kind* added to *rejects* (None stays None quietly)."""
    if value is None:
        return None
    if lim.within(value, limit, open_low=open_low):
        return value
    rejects.append(kind)
    return None


def checked_int(value: float | None, limit: lim.Limit, kind: str, rejects: list[str]) -> int | None:
    """An integer field within *limit*, or None (a fraction or a value out of range is rejected)."""
    value = checked(value, limit, kind, rejects)
    if value is None:
        return None
    if not value.is_integer():
        rejects.append(kind)
        return None
    return int(value)


def dop(value: float | None, kind: str, rejects: list[str]) -> float | None:
    """A dilution of precision, or None: 99 and up is the receivers' "unknown" (not counted), <= 0 is rejected."""
    if value is None or 99.0 <= value < 100.0:
        return None
    return checked(value, lim.DOP, kind, rejects, open_low=True)


def _decimals(sentence: Sentence) -> int:
    index = _LAT_FIELD[sentence.kind]
    raw = sentence.fields[index] if len(sentence.fields) > index else ""
    point = raw.find(".")
    return 0 if point < 0 else len(raw) - point - 1


def indicator_status(status: str, mode: str) -> str:
    """The status an RMC/GLL gives by its status letter (A/V) and mode indicator (A, D, E, N ...)."""
    if mode in MODE_STATUS:
        return MODE_STATUS[mode]
    if status == "A" and (mode == "" or mode in FIX_MODES):
        return "gnss"
    return "none"


def read_report(sentence: Sentence) -> PositionReport:
    """The :class:`PositionReport` of one GGA, GNS, RMC or GLL sentence."""
    msg, kind = sentence.msg, sentence.kind
    rep = PositionReport(kind=kind, talker=sentence.talker)
    rejects = rep.rejects
    if kind == "GGA":
        rep.quality = checked_int(num(msg, "quality", "quality", rejects), lim.GGA_QUALITY, "quality", rejects)
        rep.status = GGA_STATUS.get(rep.quality, "none") if rep.quality is not None else "none"
    elif kind == "GNS":
        modes = text(msg, "posMode").upper()
        if any(c in FIX_MODES for c in modes):
            rep.status = "gnss"
        else:
            rep.status = next((MODE_STATUS[c] for c in modes if c in MODE_STATUS and c != "N"), "none")
    else:
        rep.status = indicator_status(text(msg, "status").upper(), text(msg, "posMode").upper()[:1])
    rep.lat = checked(num(msg, "lat", "lat", rejects), lim.LAT_DEG, "lat", rejects)
    rep.lon = checked(num(msg, "lon", "lon", rejects), lim.LON_DEG, "lon", rejects)
    rep.decimals = _decimals(sentence)
    if kind in ("GGA", "GNS"):
        rep.satellites = checked_int(num(msg, "numSV", "satellites", rejects), lim.SATELLITES, "satellites", rejects)
        rep.hdop = dop(num(msg, "HDOP", "hdop", rejects), "hdop", rejects)
        rep.alt_msl = checked(num(msg, "alt", "altitude", rejects), lim.ALT_M, "altitude", rejects)
        rep.geoid_sep = checked(num(msg, "sep", "geoid separation", rejects), lim.GEOID_SEP_M, "geoid separation", rejects)
        if rep.status == "gnss" and (rep.satellites < MIN_SATELLITES if rep.satellites is not None
                                     else "satellites" in rejects):
            rep.status = "none"   # too few satellites (an empty count is unknown: the quality decides)
    return rep
