"""One GNSS epoch (GGA, RMC, VTG, GSA, GST, GNS, ZDA, HDT from any talker) to a fix and a State Information.

Pure functions, no I/O: :func:`fix_from_epoch` reads what the epoch's sentences say into
a :class:`GpsFix`; :func:`state_from_fix` turns a fix into the message the driver publishes.

Which sentence wins:

- position: GGA, else GNS, else RMC (RMC has no altitude); pynmeagps gives lat/lon in
  signed degrees (S and W negative). A fix needs a usable GGA quality (1 GPS, 2 DGPS,
  3 PPS, 4 RTK fixed, 5 RTK float, 8 simulator; 0 invalid, 6 dead reckoning and 7 manual
  are not a measurement), a GNS mode letter in ``ADPRFS``, or RMC status ``A`` with a
  mode other than ``N``/``E``; and numeric lat/lon.
- fix dimension: the highest GSA ``navMode`` (one GSA per constellation); without GSA,
  3-D when the position sentence gives an altitude.
- ground velocity: RMC speed and course, else VTG (knots, else km/h; true course).
  A course left empty at zero speed means velocity (0, 0).
- sigmas: GST ``stdLat``/``stdLong``/``stdAlt`` (m, 1 sigma) when present, else from the
  dilution of precision: per axis ``HDOP * uere / sqrt(2)`` (HDOP^2 uere^2 is the sum of
  the north and east variances), vertical ``VDOP * uere`` (``2 * HDOP * uere`` without GSA).
- true heading: HDT (dual-antenna receivers) goes into psi. Course over ground is never
  heading: it is published only as the direction of (x_dot, y_dot).
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass, field

from u2sa_hw import lcmtypes as t
from u2sa_hw.geo import GeoOrigin, geodetic_to_ned, wrap_angle
from u2sa_hw.messages import STATE_FIELDS  # noqa: F401 - installs the presence setters

from drivers.nmea_fields import Epoch, number, text, utc_time

KNOT_MPS = 1852.0 / 3600.0
GGA_QUALITY = {0: "invalid", 1: "gps", 2: "dgps", 3: "pps", 4: "rtk", 5: "float rtk", 6: "dead reckoning",
               7: "manual", 8: "simulator"}
USABLE_GGA_QUALITY = frozenset({1, 2, 3, 4, 5, 8})
GNS_FIX_MODES = frozenset("ADPRFS")
POSITION_FRAMES = ("NED", "GEODETIC")
ALTITUDE_DATUMS = ("msl", "ellipsoid")


@dataclass
class GpsFix:
    """What one epoch says. Absent values are None; ``has_fix`` False means no position."""

    has_fix: bool = False
    quality: int | None = None           # GGA quality (None without GGA)
    fix_dim: int = 0                     # 0 no fix, 2, 3
    lat: float | None = None             # degrees
    lon: float | None = None
    alt_msl: float | None = None         # m above the geoid (GGA/GNS altitude)
    geoid_sep: float | None = None       # m, ellipsoid minus geoid
    satellites: int | None = None
    hdop: float | None = None
    vdop: float | None = None
    pdop: float | None = None
    speed_mps: float | None = None
    course_deg: float | None = None      # true, clockwise from north
    heading_deg: float | None = None     # HDT true heading
    std_lat: float | None = None         # GST, m
    std_lon: float | None = None
    std_alt: float | None = None
    utc_time: dt.time | None = None
    utc_date: dt.date | None = None
    talkers: set[str] = field(default_factory=set)
    kinds: list[str] = field(default_factory=list)

    def altitude(self, datum: str) -> float | None:
        """Altitude in m up: above the geoid (``msl``) or the WGS84 ellipsoid (``ellipsoid``)."""
        if self.alt_msl is None:
            return None
        if datum == "ellipsoid":
            return self.alt_msl + (self.geoid_sep or 0.0)
        return self.alt_msl

    @property
    def fix_name(self) -> str:
        """``"no fix"``, ``"2D"`` or ``"3D"``."""
        return f"{self.fix_dim}D" if self.has_fix and self.fix_dim else "no fix"


def _position(epoch: Epoch, fix: GpsFix) -> None:
    gga, gns, rmc = epoch.first("GGA"), epoch.first("GNS"), epoch.first("RMC")
    lat = lon = None
    if gga is not None:
        q = number(gga, "quality")
        fix.quality = None if q is None else int(q)
        fix.satellites = _int(number(gga, "numSV"))
        fix.hdop = number(gga, "HDOP")
        lat, lon = number(gga, "lat"), number(gga, "lon")
        usable = fix.quality in USABLE_GGA_QUALITY
        fix.alt_msl, fix.geoid_sep = number(gga, "alt"), number(gga, "sep")
    elif gns is not None:
        usable = any(c in GNS_FIX_MODES for c in text(gns, "posMode").upper())
        fix.satellites = _int(number(gns, "numSV"))
        fix.hdop = number(gns, "HDOP")
        lat, lon = number(gns, "lat"), number(gns, "lon")
        fix.alt_msl, fix.geoid_sep = number(gns, "alt"), number(gns, "sep")
    elif rmc is not None:
        usable = text(rmc, "status").upper() == "A" and text(rmc, "posMode").upper() not in ("N", "E")
        lat, lon = number(rmc, "lat"), number(rmc, "lon")
    else:
        usable = False
    fix.has_fix = usable and lat is not None and lon is not None
    if fix.has_fix:
        fix.lat, fix.lon = lat, lon
    else:
        fix.alt_msl = fix.geoid_sep = None


def _int(value: float | None) -> int | None:
    return None if value is None else int(value)


def _dilution(epoch: Epoch, fix: GpsFix) -> None:
    modes = [m for m in (number(g, "navMode") for g in epoch.all("GSA")) if m is not None]
    for g in epoch.all("GSA"):
        fix.pdop = fix.pdop if fix.pdop is not None else number(g, "PDOP")
        fix.hdop = fix.hdop if fix.hdop is not None else number(g, "HDOP")
        fix.vdop = fix.vdop if fix.vdop is not None else number(g, "VDOP")
    if not fix.has_fix:
        fix.fix_dim = 0
    elif modes:
        fix.fix_dim = 3 if max(modes) >= 3 else 2
    else:
        fix.fix_dim = 3 if fix.alt_msl is not None else 2
    if fix.fix_dim != 3:
        fix.alt_msl = None


def _velocity(epoch: Epoch, fix: GpsFix) -> None:
    rmc, vtg = epoch.first("RMC"), epoch.first("VTG")
    speed = course = None
    if rmc is not None and text(rmc, "status").upper() == "A":
        knots = number(rmc, "spd")
        speed, course = (None if knots is None else knots * KNOT_MPS), number(rmc, "cog")
    if speed is None and vtg is not None and text(vtg, "posMode").upper() != "N":
        knots, kmh = number(vtg, "sogn"), number(vtg, "sogk")
        speed = knots * KNOT_MPS if knots is not None else (kmh / 3.6 if kmh is not None else None)
        course = number(vtg, "cogt")
    if speed is None or (course is None and speed > 0.0):
        return
    fix.speed_mps, fix.course_deg = speed, (course if course is not None else 0.0)


def _errors(epoch: Epoch, fix: GpsFix) -> None:
    gst = epoch.first("GST")
    if gst is not None:
        fix.std_lat, fix.std_lon, fix.std_alt = number(gst, "stdLat"), number(gst, "stdLong"), number(gst, "stdAlt")


def _time(epoch: Epoch, fix: GpsFix) -> None:
    fix.utc_time = epoch.time or next((w for w in (utc_time(s.msg) for s in epoch.sentences) if w), None)
    zda, rmc = epoch.first("ZDA"), epoch.first("RMC")
    if zda is not None:
        d, m, y = (_int(number(zda, k)) for k in ("day", "month", "year"))
        try:
            fix.utc_date = dt.date(y, m, d) if None not in (d, m, y) else None
        except ValueError:
            fix.utc_date = None
    if fix.utc_date is None and rmc is not None and isinstance(getattr(rmc, "date", None), dt.date):
        fix.utc_date = rmc.date


def fix_from_epoch(epoch: Epoch) -> GpsFix:
    """Everything *epoch*'s sentences say about the solution (see the module docstring)."""
    fix = GpsFix(talkers=epoch.talkers(), kinds=epoch.kinds())
    _position(epoch, fix)
    _dilution(epoch, fix)
    if fix.has_fix:
        _velocity(epoch, fix)
        _errors(epoch, fix)
    hdt = epoch.first("HDT")
    if hdt is not None:
        fix.heading_deg = number(hdt, "headingT")
    _time(epoch, fix)
    return fix


@dataclass(frozen=True)
class StateSettings:
    """How a fix becomes a State Information (the driver's config)."""

    origin: GeoOrigin
    position_frame: str = "NED"
    altitude_datum: str = "msl"
    uere_m: float = 3.0
    speed_sigma_mps: float = 0.1
    heading_sigma_deg: float = 0.5


def _sigmas(fix: GpsFix, uere: float) -> tuple[float | None, float | None, float | None]:
    if fix.std_lat is not None and fix.std_lon is not None:
        return fix.std_lat, fix.std_lon, fix.std_alt
    if fix.hdop is None:
        return None, None, None
    axis = fix.hdop * uere / math.sqrt(2.0)
    vertical = fix.vdop * uere if fix.vdop is not None else 2.0 * fix.hdop * uere
    return axis, axis, vertical


def horizontal_sigma(fix: GpsFix, uere_m: float) -> float | None:
    """The horizontal 1-sigma error (m, DRMS: the root of the north and east variances), or None.

    From GST when the epoch has it, else ``HDOP * uere``; None without a fix or either source.
    """
    if not fix.has_fix:
        return None
    sx, sy, _ = _sigmas(fix, uere_m)
    return None if sx is None or sy is None else math.hypot(sx, sy)


def state_from_fix(fix: GpsFix, settings: StateSettings) -> t.StateInformation | None:
    """The State Information for *fix*, or None when it measures nothing (no fix and no heading)."""
    msg = t.StateInformation()
    if fix.has_fix and fix.lat is not None and fix.lon is not None:
        alt = fix.altitude(settings.altitude_datum) if fix.fix_dim == 3 else None
        sx, sy, sz = _sigmas(fix, settings.uere_m)
        if settings.position_frame == "GEODETIC":
            msg.reference_frame = "GEODETIC"
            msg.set(x=fix.lat, y=fix.lon)
            if alt is not None:
                msg.set(z=alt)
        else:
            msg.reference_frame = "NED"
            north, east, down = geodetic_to_ned(fix.lat, fix.lon, alt, origin=settings.origin)
            msg.set(x=north, y=east)
            if alt is not None:
                msg.set(z=down)
        for name, sigma in (("x_sigma", sx), ("y_sigma", sy)):
            if sigma is not None and sigma > 0:
                msg.set(**{name: sigma})
        if alt is not None and sz is not None and sz > 0:
            msg.set(z_sigma=sz)
        if fix.speed_mps is not None and fix.course_deg is not None:
            course = math.radians(fix.course_deg)
            msg.set(x_dot=fix.speed_mps * math.cos(course), y_dot=fix.speed_mps * math.sin(course),
                    x_dot_sigma=settings.speed_sigma_mps, y_dot_sigma=settings.speed_sigma_mps)
    if fix.heading_deg is not None:
        msg.set(psi=wrap_angle(math.radians(fix.heading_deg)), psi_sigma=math.radians(settings.heading_sigma_deg))
        msg.reference_frame = msg.reference_frame or "NED"
    return msg if msg.presence_vector else None
