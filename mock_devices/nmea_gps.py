"""A GNSS receiver that speaks NMEA 0183 on a pty, with its fix taken from the SimVehicle.

Each epoch draws one seeded Gaussian error (north, east, up, velocity, heading) and every
sentence of that epoch reports the same noisy solution, as a real receiver's do. Sentences
follow NMEA 0183 4.10 (RMC/GNS carry the navigational-status field, GSA has no system id)
and are assembled and checksummed by ``pynmeagps.NMEAMessage``; this module only formats
the field values (fixed decimals, as receivers print them).

Supported sentences: GGA, RMC, VTG, GSA, GST, ZDA, HDT (dual-antenna true heading), GNS, GLL.
Without a fix (``set_fix(False)``) the receiver still sends every sentence with the time,
but empty position fields, GGA quality 0, RMC/GLL status V, mode N and GSA 1 (no fix).

``set_quality(q)`` makes the fix a GGA quality *q* with the matching mode letter in
RMC/GNS/GLL/VTG (6 dead reckoning: ``E``, 8 simulator: ``S``, 2 DGPS: ``D``, 4 RTK: ``R``,
5 float RTK: ``F``); ``geoid_separation_m=None`` leaves the GGA/GNS geoid field empty (older
SiRF and MTK receivers); ``inject(line)`` writes any line between epochs (a crafted sentence).

Magnetic fields (RMC variation, VTG magnetic course) use ``declination_deg``: east positive,
true = magnetic + declination. With ``declination_deg=None`` they are left empty, as most
receivers do.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Callable, ClassVar

from pynmeagps import NMEAMessage
from pynmeagps.nmeahelpers import ddd2dmm, time2str

from u2sa_hw.mocks.pty_serial import PeriodicSerialDevice
from u2sa_hw.mocks.vehicle_sim import SimVehicle, VehicleTruth, ned_to_geodetic

GPS_SENTENCES = ("GGA", "RMC", "VTG", "GSA", "GST", "ZDA", "HDT", "GNS", "GLL")
KNOT_MPS = 1852.0 / 3600.0
_SATELLITES = (2, 5, 7, 9, 13, 15, 18, 20, 24, 27, 29, 30)  # PRNs reported as used in GSA
MODE_LETTERS = {1: "A", 2: "D", 3: "P", 4: "R", 5: "F", 6: "E", 7: "M", 8: "S"}  # GGA quality -> NMEA mode


def nmea_sentence(talker: str, msg_id: str, fields: list[str]) -> bytes:
    """``$<talker><msg_id>,<fields>*HH\\r\\n`` assembled and checksummed by pynmeagps."""
    return NMEAMessage(talker, msg_id, 0, payload=list(fields)).serialize()


def heading_360(deg: float, *, decimals: int) -> float:
    """*deg* wrapped into [0, 360) after rounding to *decimals*, so printing never shows 360.0."""
    return round(deg % 360.0, decimals) % 360.0


@dataclass(frozen=True)
class GpsSolution:
    """One epoch's noisy fix: lat/lon degrees, alt m, speed m/s, course and heading degrees true."""

    lat: float
    lon: float
    alt: float
    speed: float
    course_deg: float
    heading_deg: float


class NmeaGpsDevice(PeriodicSerialDevice):
    """A mock NMEA GNSS receiver at *link_path*, sampling *vehicle* at *rate_hz*."""

    PROTOCOL: ClassVar[str] = "nmea"
    """What it speaks: the mock catalog refuses it for a driver whose declared ``protocol`` differs."""

    def __init__(self, vehicle: SimVehicle, *, link_path: str | os.PathLike[str], rate_hz: float = 5.0,
                 talker: str = "GP", sentences: tuple[str, ...] = ("GGA", "RMC", "VTG", "GSA", "GST", "ZDA", "HDT"),
                 horizontal_sigma_m: float = 1.5, vertical_sigma_m: float = 3.0, speed_sigma_mps: float = 0.05,
                 heading_sigma_deg: float = 0.2, declination_deg: float | None = None, num_satellites: int = 10,
                 hdop: float = 0.9, vdop: float = 1.4, geoid_separation_m: float | None = 0.0, seed: int = 0,
                 fix: bool = True, utc_clock: Callable[[], datetime] | None = None, name: str = "gps") -> None:
        unknown = [s for s in sentences if s not in GPS_SENTENCES]
        if unknown:
            raise ValueError(f"{name}: unsupported NMEA sentence(s) {unknown}; choose from {', '.join(GPS_SENTENCES)}")
        if len(talker) != 2 or not talker.isalpha():
            raise ValueError(f"{name}: talker must be two letters like 'GP' or 'GN', got {talker!r}")
        for label, value in (("horizontal_sigma_m", horizontal_sigma_m), ("vertical_sigma_m", vertical_sigma_m),
                             ("speed_sigma_mps", speed_sigma_mps), ("heading_sigma_deg", heading_sigma_deg)):
            if not value >= 0:
                raise ValueError(f"{name}: {label} must be >= 0, got {value!r}")
        super().__init__(vehicle, link_path=link_path, rate_hz=rate_hz, name=name, seed=seed)
        self.talker = talker.upper()
        self.sentences = tuple(sentences)
        self.horizontal_sigma_m = float(horizontal_sigma_m)
        self.vertical_sigma_m = float(vertical_sigma_m)
        self.speed_sigma_mps = float(speed_sigma_mps)
        self.heading_sigma_deg = float(heading_sigma_deg)
        self.declination_deg = declination_deg
        self.num_satellites = max(0, min(len(_SATELLITES), int(num_satellites)))
        self.hdop, self.vdop = float(hdop), float(vdop)
        self.geoid_separation_m = None if geoid_separation_m is None else float(geoid_separation_m)
        self.quality = 1
        self.utc_clock = utc_clock or (lambda: datetime.now(timezone.utc))
        self._fix = bool(fix)

    # ---- faults ----------------------------------------------------------------------
    def set_fix(self, on: bool) -> None:
        """Have a position fix (True) or report no fix (False: GGA quality 0, RMC status V)."""
        self._fix = bool(on)

    def set_quality(self, quality: int) -> None:
        """Report the fix with GGA quality *quality* (1-8) and its mode letter (6: dead reckoning, 8: simulator)."""
        if quality not in MODE_LETTERS:
            raise ValueError(f"{self.name}: GGA quality must be one of 1-8, got {quality!r}")
        self.quality = int(quality)

    def inject(self, line: bytes) -> int:
        """Write *line* (a complete sentence of the test's making) now, between epochs."""
        return self.link.write(line)

    @property
    def _mode(self) -> str:
        return MODE_LETTERS[self.quality]

    @property
    def _sep(self) -> str:
        return "" if self.geoid_separation_m is None else f"{self.geoid_separation_m:.1f}"

    @property
    def has_fix(self) -> bool:
        """True while the receiver reports a fix."""
        return self._fix

    # ---- one epoch -------------------------------------------------------------------
    def solve(self, truth: VehicleTruth) -> GpsSolution:
        """Draw this epoch's errors and return the noisy fix for *truth*."""
        g = self.rng.gauss
        lat, lon, alt = ned_to_geodetic(
            truth.north + g(0.0, self.horizontal_sigma_m), truth.east + g(0.0, self.horizontal_sigma_m),
            truth.down + g(0.0, self.vertical_sigma_m), origin_lat=self.vehicle.origin_lat,
            origin_lon=self.vehicle.origin_lon, origin_alt=self.vehicle.origin_alt)
        vn = truth.v_north + g(0.0, self.speed_sigma_mps)
        ve = truth.v_east + g(0.0, self.speed_sigma_mps)
        speed = math.hypot(vn, ve)
        # below a few sigma the velocity direction is noise; receivers hold the truth-like course
        course = math.atan2(ve, vn) if speed > 3.0 * self.speed_sigma_mps else truth.course
        heading = truth.yaw + math.radians(g(0.0, self.heading_sigma_deg))
        return GpsSolution(lat=lat, lon=lon, alt=alt, speed=speed,
                           course_deg=heading_360(math.degrees(course), decimals=2),
                           heading_deg=heading_360(math.degrees(heading), decimals=2))

    def epoch_lines(self, truth: VehicleTruth) -> list[bytes]:
        """Every configured sentence for one epoch, in the configured order."""
        fix = self._fix
        sol = self.solve(truth)
        now = self.utc_clock().astimezone(timezone.utc)
        builders = {"GGA": self._gga, "RMC": self._rmc, "VTG": self._vtg, "GSA": self._gsa, "GST": self._gst,
                    "ZDA": self._zda, "HDT": self._hdt, "GNS": self._gns, "GLL": self._gll}
        return [nmea_sentence(self.talker, s, builders[s](sol, now, fix)) for s in self.sentences]

    @staticmethod
    def _latlon(sol: GpsSolution, fix: bool) -> list[str]:
        if not fix:
            return ["", "", "", ""]
        return [ddd2dmm(sol.lat, "LA"), "N" if sol.lat >= 0 else "S",
                ddd2dmm(sol.lon, "LN"), "E" if sol.lon >= 0 else "W"]

    def _gga(self, sol: GpsSolution, now: datetime, fix: bool) -> list[str]:
        if not fix:
            return [time2str(now.time()), "", "", "", "", "0", "00", "99.99", "", "", "", "", "", ""]
        return [time2str(now.time()), *self._latlon(sol, fix), str(self.quality), f"{self.num_satellites:02d}",
                f"{self.hdop:.2f}", f"{sol.alt:.1f}", "M", self._sep, "M", "", ""]

    def _rmc(self, sol: GpsSolution, now: datetime, fix: bool) -> list[str]:
        dec = self.declination_deg
        mv = ["", ""] if dec is None else [f"{abs(dec):.1f}", "E" if dec >= 0 else "W"]
        motion = [f"{sol.speed / KNOT_MPS:.3f}", f"{sol.course_deg:.2f}"] if fix else ["", ""]
        return [time2str(now.time()), "A" if fix else "V", *self._latlon(sol, fix), *motion,
                now.strftime("%d%m%y"), *mv, self._mode if fix else "N", "V"]

    def _vtg(self, sol: GpsSolution, now: datetime, fix: bool) -> list[str]:
        if not fix:
            return ["", "T", "", "M", "", "N", "", "K", "N"]
        dec = self.declination_deg
        cogm = "" if dec is None else f"{heading_360(sol.course_deg - dec, decimals=2):.2f}"
        return [f"{sol.course_deg:.2f}", "T", cogm, "M", f"{sol.speed / KNOT_MPS:.3f}", "N",
                f"{sol.speed * 3.6:.3f}", "K", self._mode]

    def _gsa(self, sol: GpsSolution, now: datetime, fix: bool) -> list[str]:
        used = [f"{prn:02d}" for prn in _SATELLITES[:self.num_satellites]] if fix else []
        used += [""] * (12 - len(used))
        if not fix:
            return ["A", "1", *used, "99.99", "99.99", "99.99"]
        pdop = math.hypot(self.hdop, self.vdop)
        return ["A", "3", *used, f"{pdop:.2f}", f"{self.hdop:.2f}", f"{self.vdop:.2f}"]

    def _gst(self, sol: GpsSolution, now: datetime, fix: bool) -> list[str]:
        if not fix:
            return [time2str(now.time()), "", "", "", "", "", "", ""]
        h, v = self.horizontal_sigma_m, self.vertical_sigma_m
        return [time2str(now.time()), f"{h:.1f}", f"{h:.2f}", f"{h:.2f}", "0.0", f"{h:.2f}", f"{h:.2f}", f"{v:.2f}"]

    def _zda(self, sol: GpsSolution, now: datetime, fix: bool) -> list[str]:
        return [time2str(now.time()), f"{now.day:02d}", f"{now.month:02d}", f"{now.year:04d}", "00", "00"]

    def _hdt(self, sol: GpsSolution, now: datetime, fix: bool) -> list[str]:
        return [f"{sol.heading_deg:.2f}" if fix else "", "T"]

    def _gns(self, sol: GpsSolution, now: datetime, fix: bool) -> list[str]:
        if not fix:
            return [time2str(now.time()), "", "", "", "", "N", "00", "99.99", "", "", "", "", "V"]
        return [time2str(now.time()), *self._latlon(sol, fix), self._mode, f"{self.num_satellites:02d}",
                f"{self.hdop:.2f}", f"{sol.alt:.1f}", self._sep, "", "", "V"]

    def _gll(self, sol: GpsSolution, now: datetime, fix: bool) -> list[str]:
        return [*self._latlon(sol, fix), time2str(now.time()), "A" if fix else "V", self._mode if fix else "N"]
