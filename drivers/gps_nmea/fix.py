"""One GNSS epoch (GGA, GNS, RMC, GLL, VTG, GSA, GST, ZDA, HDT from any talkers) to a fix and a State Information.

Pure functions, no I/O: :func:`fix_from_epoch` merges what the epoch's sentences say into
a :class:`GpsFix`; :func:`state_from_fix` turns a fix into the message the driver publishes.
Every value is range-checked on the way in (``u2sa_hw.drivers.gps_nmea.limits``); what was dropped is
in ``GpsFix.rejects``. docs/drivers-serial.md lists these rules beside gpsd's.

Merging the sentences of one epoch (one UTC time):

- *status*: each position sentence is read on its own (``u2sa_hw.drivers.gps_nmea.reports``). The
  epoch has a GNSS fix when any of them has one; the richest of those is the *primary*
  (an altitude, then more satellites, then GGA > GNS > RMC > GLL), so a later sentence with
  less content (a second talker's GGA without altitude, an RMC) never downgrades the fix.
  Without a GNSS fix the status is dead reckoning, simulator or manual when a sentence
  says so (none of them is a measurement: no position is published), else no fix. When
  the epoch has GGA or GNS and none of them has a GNSS fix, they decide: an RMC or GLL
  status A beside them does not make a fix (fail safe; they carry the quality).
  Every GSA saying "no fix" (navMode 1) vetoes the fix (fail safe).
- *position*: latitude and longitude of the primary, or of another fix sentence of the
  epoch that gives the same position with more decimals (an RMC with 5 decimals beside a
  GGA with 4); altitude, satellites and HDOP of the primary.
- *dimension*: 3-D when the primary has an altitude and either at least 4 satellites in
  use (gpsd's rule) or a GSA says 3-D; a GSA saying 2-D does not take the altitude away
  from a GGA with 4 satellites. Otherwise 2-D: no altitude is published (an epoch without
  GGA or GNS; an altitude with 3 satellites, or an empty count, and no GSA saying 3-D).
  ``GpsFix.fix_rule`` names the rule that gave the fix mode (the ``RULE_*`` texts below;
  docs/drivers-serial.md has the policy beside gpsd's, and why it differs).
- *geoid*: the receiver's geoid separation, else the built-in EGM96 table
  (``u2sa_hw.drivers.gps_nmea.geoid``), so the ellipsoid height is right with any receiver.
- *velocity*: speed and course are separate fields: speed from RMC, else VTG (knots,
  else km/h); course from RMC, else VTG (true). VTG or RMC marked not valid, estimated or
  simulated gives neither.
- *sigmas*: GST ``stdLat``/``stdLong``/``stdAlt`` (m, 1 sigma), else per axis
  ``HDOP * uere / sqrt(2)`` and vertically ``VDOP * uere`` (``2 * HDOP * uere`` without VDOP).
- *heading*: HDT (dual-antenna receivers) goes into psi. Course over ground is never heading.
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass, field

from u2sa_hw import lcmtypes as t
from u2sa_hw.geo import GeoOrigin, geodetic_to_ned, wrap_angle
from u2sa_hw.messages import STATE_FIELDS  # noqa: F401 - installs the presence setters

from u2sa_hw.drivers.gps_nmea import limits as lim
from u2sa_hw.drivers.gps_nmea.geoid import geoid_separation
from u2sa_hw.drivers.gps_nmea.reports import (MIN_SATELLITES_3D, POSITION_KINDS, PositionReport, checked, checked_int, dop,
                                 indicator_status, num, read_report)
from u2sa_hw.drivers.nmea_fields import Epoch, text, utc_time

KNOT_MPS = 1852.0 / 3600.0
GGA_QUALITY = {0: "invalid", 1: "gps", 2: "dgps", 3: "pps", 4: "rtk", 5: "float rtk", 6: "dead reckoning",
               7: "manual", 8: "simulator"}
STATUS_NAMES = {"dr": "DR", "simulator": "simulator", "manual": "manual"}
# Which rule gave an epoch its fix mode (GpsFix.fix_rule; health ``fix_rule``). 3-D:
RULE_3D_SATELLITES = "altitude, 4+ satellites"
RULE_3D_OVER_GSA_2D = "altitude, 4+ satellites over a GSA saying 2D"
RULE_3D_GSA = "altitude, a GSA saying 3D"
# 2-D (no altitude published):
RULE_2D_NO_GGA = "no GGA or GNS (no altitude)"
RULE_2D_NO_ALTITUDE = "GGA/GNS without altitude"
RULE_2D_FEW_SATELLITES = "altitude with under 4 satellites, no GSA saying 3D"
RULE_2D_UNKNOWN_SATELLITES = "altitude with no satellite count, no GSA saying 3D"
# no fix (or dead reckoning, simulator, manual: no position published):
RULE_NONE_GGA = "GGA/GNS quality, mode or under 3 satellites"
RULE_NONE_STATUS = "RMC/GLL status or mode"
RULE_NONE_GSA = "every GSA says no fix"
VELOCITY_INVALID_MODES = frozenset("NESM")
POSITION_FRAMES = ("NED", "GEODETIC")
ALTITUDE_DATUMS = ("msl", "ellipsoid")


@dataclass
class GpsFix:
    """What one epoch says. Absent values are None; ``has_fix`` False means no position."""

    has_fix: bool = False
    status: str = "none"                 # gnss, dr, simulator, manual, none
    reported: bool = False               # the epoch held a position sentence (else it says nothing of the fix)
    quality: int | None = None           # GGA quality (None without GGA)
    fix_dim: int = 0                     # 0 no fix, 2, 3
    fix_rule: str = ""                   # the rule that gave fix_dim / status (a RULE_* text; "" says nothing)
    lat: float | None = None             # degrees
    lon: float | None = None
    alt_msl: float | None = None         # m above the geoid (GGA/GNS altitude)
    geoid_sep: float | None = None       # m, ellipsoid minus geoid
    geoid_source: str = ""               # "receiver" or "EGM96 table"
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
    rejects: list[str] = field(default_factory=list)   # kinds of values dropped as out of range

    def altitude(self, datum: str) -> float | None:
        """Altitude in m up: above the geoid (``msl``) or the WGS84 ellipsoid (``ellipsoid``)."""
        if self.alt_msl is None:
            return None
        if datum == "ellipsoid":
            return self.alt_msl + (self.geoid_sep or 0.0)
        return self.alt_msl

    @property
    def fix_name(self) -> str:
        """``"no fix"``, ``"2D"``, ``"3D"``, or ``"DR"``, ``"simulator"``, ``"manual"`` (not measurements)."""
        if self.has_fix and self.fix_dim:
            return f"{self.fix_dim}D"
        return STATUS_NAMES.get(self.status, "no fix")


def _finer_position(primary: PositionReport, reports: list[PositionReport]) -> tuple[float, float]:
    """The primary's lat/lon, or the same position with more decimals from another fix sentence."""
    lat, lon = primary.lat, primary.lon
    assert lat is not None and lon is not None
    best = primary
    for rep in reports:
        if rep.is_fix and rep.decimals > best.decimals and rep.lat is not None and rep.lon is not None:
            tolerance = 1.5 * 10.0 ** -primary.decimals / 60.0   # a unit of the primary's last digit, in degrees
            if abs(rep.lat - lat) <= tolerance and abs(rep.lon - lon) <= tolerance:
                best = rep
    assert best.lat is not None and best.lon is not None
    return best.lat, best.lon


def _position(epoch: Epoch, fix: GpsFix) -> None:
    reports = [read_report(s) for s in epoch.sentences if s.kind in POSITION_KINDS]
    for rep in reports:
        fix.rejects.extend(rep.rejects)
    fix.reported = bool(reports)
    ggas = [r for r in reports if r.kind == "GGA"]
    fix.quality = ggas[0].quality if ggas else None
    fixes = [r for r in reports if r.is_fix]
    rich = [r for r in reports if r.kind in ("GGA", "GNS")]
    if rich and not any(r.is_fix for r in rich):
        # GGA/GNS carry the fix quality: when they all say no GNSS fix (0, dead reckoning, too few
        # satellites), an RMC/GLL status A (NMEA 2.0 has no mode letter for DR) does not make one
        fixes, reports = [], rich
    if not fixes:
        statuses = {r.status for r in reports}
        fix.status = next((s for s in ("dr", "simulator", "manual") if s in statuses), "none")
        fix.satellites = next((r.satellites for r in reports if r.satellites is not None), None)
        if reports:
            fix.fix_rule = RULE_NONE_GGA if rich else RULE_NONE_STATUS
        return
    primary = max(fixes, key=PositionReport.richness)   # max keeps the first of equals: arrival order
    fix.has_fix, fix.status = True, "gnss"
    if primary.kind in ("RMC", "GLL"):
        fix.fix_rule = RULE_2D_NO_GGA   # the richest fix sentence has no altitude field: no GGA or GNS
    fix.quality = primary.quality if primary.kind == "GGA" else fix.quality
    fix.lat, fix.lon = _finer_position(primary, fixes)
    fix.alt_msl, fix.satellites = primary.alt_msl, primary.satellites
    fix.hdop = primary.hdop if primary.hdop is not None else next((r.hdop for r in fixes if r.hdop), None)
    if primary.geoid_sep is not None:
        fix.geoid_sep, fix.geoid_source = primary.geoid_sep, "receiver"
    else:
        fix.geoid_sep, fix.geoid_source = geoid_separation(fix.lat, fix.lon), "EGM96 table"


def _dilution(epoch: Epoch, fix: GpsFix) -> None:
    modes: list[int] = []
    for g in epoch.all("GSA"):
        mode = checked_int(num(g, "navMode", "gsa mode", fix.rejects), lim.Limit(1.0, 3.0), "gsa mode", fix.rejects)
        if mode is not None:
            modes.append(mode)
        fix.pdop = fix.pdop if fix.pdop is not None else dop(num(g, "PDOP", "pdop", fix.rejects), "pdop", fix.rejects)
        fix.hdop = fix.hdop if fix.hdop is not None else dop(num(g, "HDOP", "hdop", fix.rejects), "hdop", fix.rejects)
        fix.vdop = fix.vdop if fix.vdop is not None else dop(num(g, "VDOP", "vdop", fix.rejects), "vdop", fix.rejects)
    gsa_mode = max(modes) if modes else 0
    if fix.has_fix and gsa_mode == 1:
        fix.has_fix, fix.status = False, "none"     # the receiver says no fix in every GSA: fail safe
        fix.fix_rule = RULE_NONE_GSA
    if not fix.has_fix:
        fix.fix_dim = 0
        fix.lat = fix.lon = fix.alt_msl = fix.geoid_sep = None
        fix.geoid_source = ""
        return
    # the fix mode (docs/drivers-serial.md, "Fix mode"): 3-D needs an altitude and either 4 satellites
    # or the receiver's GSA saying 3-D; else 2-D, and the altitude is not published
    if fix.alt_msl is None:
        fix.fix_dim, fix.fix_rule = 2, fix.fix_rule or RULE_2D_NO_ALTITUDE
    elif fix.satellites is not None and fix.satellites >= MIN_SATELLITES_3D:
        fix.fix_dim, fix.fix_rule = 3, RULE_3D_OVER_GSA_2D if gsa_mode == 2 else RULE_3D_SATELLITES
    elif gsa_mode == 3:
        fix.fix_dim, fix.fix_rule = 3, RULE_3D_GSA
    else:
        fix.fix_dim, fix.alt_msl = 2, None
        fix.fix_rule = RULE_2D_UNKNOWN_SATELLITES if fix.satellites is None else RULE_2D_FEW_SATELLITES


def _velocity(epoch: Epoch, fix: GpsFix) -> None:
    speed = course = None
    for rmc in epoch.all("RMC"):
        if indicator_status(text(rmc, "status").upper(), text(rmc, "posMode").upper()[:1]) != "gnss":
            continue
        knots = num(rmc, "spd", "speed", fix.rejects)
        speed = speed if speed is not None or knots is None else knots * KNOT_MPS
        course = course if course is not None else num(rmc, "cog", "course", fix.rejects)
    for vtg in epoch.all("VTG"):
        if text(vtg, "posMode").upper()[:1] in VELOCITY_INVALID_MODES:
            continue
        if speed is None:
            knots, kmh = num(vtg, "sogn", "speed", fix.rejects), num(vtg, "sogk", "speed", fix.rejects)
            speed = knots * KNOT_MPS if knots is not None else (kmh / 3.6 if kmh is not None else None)
        course = course if course is not None else num(vtg, "cogt", "course", fix.rejects)
    fix.speed_mps = checked(speed, lim.SPEED_MPS, "speed", fix.rejects)
    course = checked(course, lim.ANGLE_DEG, "course", fix.rejects)
    fix.course_deg = None if course is None else course % 360.0


def _errors(epoch: Epoch, fix: GpsFix) -> None:
    gst = epoch.first("GST")
    if gst is None:
        return
    values = []
    for name, kind in (("stdLat", "sigma lat"), ("stdLong", "sigma lon"), ("stdAlt", "sigma alt")):
        value = num(gst, name, kind, fix.rejects)
        values.append(None if value == 0.0 else checked(value, lim.SIGMA_M, kind, fix.rejects, open_low=True))
    fix.std_lat, fix.std_lon, fix.std_alt = values


def _time(epoch: Epoch, fix: GpsFix) -> None:
    fix.utc_time = epoch.time or next((w for w in (utc_time(s.msg) for s in epoch.sentences) if w), None)
    for zda in epoch.all("ZDA"):
        d, m = (checked_int(num(zda, k, "date", fix.rejects), lim.Limit(1.0, 31.0), "date", fix.rejects)
                for k in ("day", "month"))
        y = checked_int(num(zda, "year", "date", fix.rejects), lim.DATE_YEAR, "date", fix.rejects)
        if None not in (d, m, y):
            try:
                fix.utc_date = dt.date(y, m, d)  # type: ignore[arg-type]
                break
            except (ValueError, OverflowError):
                fix.rejects.append("date")
    if fix.utc_date is None:
        fix.utc_date = next((r.date for r in epoch.all("RMC") if isinstance(getattr(r, "date", None), dt.date)),
                            None)


def fix_from_epoch(epoch: Epoch) -> GpsFix:
    """Everything *epoch*'s sentences say about the solution (see the module docstring)."""
    fix = GpsFix(talkers=epoch.talkers(), kinds=epoch.kinds())
    _position(epoch, fix)
    _dilution(epoch, fix)
    if fix.has_fix:
        _velocity(epoch, fix)
        _errors(epoch, fix)
    for hdt in epoch.all("HDT"):
        heading = checked(num(hdt, "headingT", "heading", fix.rejects), lim.ANGLE_DEG, "heading", fix.rejects)
        if heading is not None:
            fix.heading_deg = heading % 360.0
            break
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


def _set_velocity(msg: t.StateInformation, fix: GpsFix, sigma: float) -> None:
    speed = fix.speed_mps
    if speed is None:
        return
    if fix.course_deg is not None:
        course = math.radians(fix.course_deg)
        msg.set(x_dot=speed * math.cos(course), y_dot=speed * math.sin(course), x_dot_sigma=sigma, y_dot_sigma=sigma)
    else:
        # A speed without a course (a receiver at rest leaves the course empty): the direction is
        # unknown, so each axis is 0 with the spread of a vector of that length in any direction.
        spread = math.hypot(sigma, speed / math.sqrt(2.0))
        msg.set(x_dot=0.0, y_dot=0.0, x_dot_sigma=spread, y_dot_sigma=spread)


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
        _set_velocity(msg, fix, settings.speed_sigma_mps)
    if fix.heading_deg is not None:
        msg.set(psi=wrap_angle(math.radians(fix.heading_deg)), psi_sigma=math.radians(settings.heading_sigma_deg))
        msg.reference_frame = msg.reference_frame or "NED"
    return msg if msg.presence_vector else None
