"""Serial compasses on a pty: an NMEA 0183 heading sensor and an OceanServer OS5000.

Both take the heading from the SimVehicle's yaw (true, clockwise from north) with seeded
Gaussian noise. Sign convention (as on charts and in NMEA): declination/variation and
deviation are east positive, and

    true heading     = magnetic heading + declination
    magnetic heading = compass (sensor) heading + deviation

so a compass in a place with 10 deg E declination reads 350 deg when the vehicle points
true north.

``NmeaCompassDevice`` sends any of HDG (sensor heading with deviation and variation
fields), HDM (magnetic), HDT (true), THS (true, mode A), ROT (the yaw rate in deg/min),
XDR (pitch and roll as angle transducers "PITCH"/"ROLL", degrees), PASHR (true heading,
roll, pitch, heave 0 and the sigmas as accuracies) and PTNTHTM/PTNTHPR (the magnetic
heading as a TNT/HMR3000 without variation programmed sends it, status N), in the order
given -- e.g. ``("XDR", "HDM")`` for a compass that sends its attitude first; talker "HC"
by default, built and checksummed by pynmeagps.

``Os5000CompassDevice`` sends the OS5000's default ASCII output
``$C<heading>P<pitch>R<roll>T<temp>*<checksum>`` CR LF: magnetic heading, pitch and roll in
degrees with one decimal, board temperature in degrees C, and the NMEA-style checksum (XOR
of the characters between ``$`` and ``*``, two hex digits). Its configuration commands
(ESC sequences) are not modelled; what a driver writes is kept in ``link.history``.

With ``raw_field=True`` the OS5000 also sends ``Mx``/``My``/``Mz``: the Earth field
``earth_field_mg`` (NED, mG) rotated into the body (FRD) by the vehicle's attitude and
distorted by the vehicle's iron, ``soft_iron @ field + hard_iron_mg`` (defaults identity and
zero), so a calibration can be checked against a known truth.

Pitch is positive nose up and roll positive right side down; the SimVehicle is level, so
both are 0 plus noise.
"""

from __future__ import annotations

import math
import os
from typing import ClassVar

from pynmeagps.nmeahelpers import calc_checksum

from u2sa_hw.mocks.nmea_gps import heading_360, nmea_sentence
from u2sa_hw.mocks.pty_serial import PeriodicSerialDevice
from u2sa_hw.mocks.vehicle_sim import SimVehicle, VehicleTruth

COMPASS_SENTENCES = ("HDG", "HDM", "HDT", "THS", "ROT", "XDR", "PASHR", "PTNTHTM", "PTNTHPR")


def one_decimal(value: float) -> str:
    """*value* with one decimal, never "-0.0" (a small negative noise rounds to "0.0")."""
    return f"{round(value, 1) + 0.0:.1f}"


class _CompassBase(PeriodicSerialDevice):
    """Shared noise model: true heading, magnetic heading, pitch and roll for one epoch."""

    def __init__(self, vehicle: SimVehicle, *, link_path: str | os.PathLike[str], rate_hz: float, name: str,
                 declination_deg: float, heading_sigma_deg: float, attitude_sigma_deg: float, seed: int) -> None:
        for label, value in (("heading_sigma_deg", heading_sigma_deg), ("attitude_sigma_deg", attitude_sigma_deg)):
            if not value >= 0:
                raise ValueError(f"{name}: {label} must be >= 0, got {value!r}")
        if not math.isfinite(declination_deg):
            raise ValueError(f"{name}: declination_deg must be a finite number (east positive), "
                             f"got {declination_deg!r}")
        super().__init__(vehicle, link_path=link_path, rate_hz=rate_hz, name=name, seed=seed)
        self.declination_deg = float(declination_deg)
        self.heading_sigma_deg = float(heading_sigma_deg)
        self.attitude_sigma_deg = float(attitude_sigma_deg)

    def measure(self, truth: VehicleTruth) -> tuple[float, float, float]:
        """This epoch's (magnetic heading, pitch, roll) in degrees, noise drawn once."""
        g = self.rng.gauss
        true_heading = math.degrees(truth.yaw) + g(0.0, self.heading_sigma_deg)
        magnetic = heading_360(true_heading - self.declination_deg, decimals=1)
        pitch = math.degrees(truth.pitch) + g(0.0, self.attitude_sigma_deg)
        roll = math.degrees(truth.roll) + g(0.0, self.attitude_sigma_deg)
        return magnetic, pitch, roll


class NmeaCompassDevice(_CompassBase):
    """A mock NMEA 0183 heading sensor at *link_path* (HDG/HDM/HDT, optional XDR pitch/roll)."""

    PROTOCOL: ClassVar[str] = "nmea"
    """What it speaks: the mock catalog refuses it for a driver whose declared ``protocol`` differs."""

    def __init__(self, vehicle: SimVehicle, *, link_path: str | os.PathLike[str], rate_hz: float = 10.0,
                 talker: str = "HC", sentences: tuple[str, ...] = ("HDG",), declination_deg: float = 0.0,
                 deviation_deg: float = 0.0, heading_sigma_deg: float = 0.5, attitude_sigma_deg: float = 0.2,
                 seed: int = 0, name: str = "compass") -> None:
        unknown = [s for s in sentences if s not in COMPASS_SENTENCES]
        if unknown:
            raise ValueError(f"{name}: unsupported sentence(s) {unknown}; choose from {', '.join(COMPASS_SENTENCES)}")
        if len(talker) != 2 or not talker.isalpha():
            raise ValueError(f"{name}: talker must be two letters like 'HC' or 'II', got {talker!r}")
        if not math.isfinite(deviation_deg):
            raise ValueError(f"{name}: deviation_deg must be a finite number (east positive), got {deviation_deg!r}")
        super().__init__(vehicle, link_path=link_path, rate_hz=rate_hz, name=name, declination_deg=declination_deg,
                         heading_sigma_deg=heading_sigma_deg, attitude_sigma_deg=attitude_sigma_deg, seed=seed)
        self.talker = talker.upper()
        self.sentences = tuple(sentences)
        self.deviation_deg = float(deviation_deg)

    def epoch_lines(self, truth: VehicleTruth) -> list[bytes]:
        """Every configured sentence for one epoch, in the configured order."""
        magnetic, pitch, roll = self.measure(truth)
        lines = []
        for s in self.sentences:
            if s == "HDG":
                sensor = heading_360(magnetic - self.deviation_deg, decimals=1)
                dev, var = self.deviation_deg, self.declination_deg
                fields = [f"{sensor:.1f}", f"{abs(dev):.1f}", "E" if dev >= 0 else "W",
                          f"{abs(var):.1f}", "E" if var >= 0 else "W"]
            elif s == "HDM":
                fields = [f"{magnetic:.1f}", "M"]
            elif s in ("HDT", "THS"):
                fields = [f"{heading_360(magnetic + self.declination_deg, decimals=1):.1f}", "T" if s == "HDT" else "A"]
            elif s == "ROT":
                fields = [one_decimal(math.degrees(truth.yaw_rate) * 60.0), "A"]
            elif s == "XDR":
                fields = ["A", one_decimal(pitch), "D", "PITCH", "A", one_decimal(roll), "D", "ROLL"]
            elif s == "PASHR":
                lines.append(proprietary("PASHR", [
                    f"{truth.t % 86400 // 3600:02.0f}{truth.t % 3600 // 60:02.0f}{truth.t % 60:05.2f}",
                    f"{heading_360(magnetic + self.declination_deg, decimals=2):.2f}", "T", f"{roll:.2f}",
                    f"{pitch:.2f}", "0.00", f"{self.attitude_sigma_deg:.3f}", f"{self.attitude_sigma_deg:.3f}",
                    f"{self.heading_sigma_deg:.3f}", "1", "1"]))
                continue
            else:   # PTNTHTM / PTNTHPR: heading, mag status, pitch, status, roll, status[, dip, field]
                tnt = [f"{magnetic:.1f}", "N", one_decimal(pitch), "N", one_decimal(roll), "N"]
                lines.append(proprietary(s, tnt + (["60.0", "2500"] if s == "PTNTHTM" else [])))
                continue
            lines.append(nmea_sentence(self.talker, s, fields))
        return lines


def proprietary(address: str, fields: list[str]) -> bytes:
    """``$<address>,<fields>*HH`` CR LF (a proprietary sentence has no talker id)."""
    body = ",".join([address, *fields])
    return f"${body}*{calc_checksum(body)}\r\n".encode("ascii")


def os5000_line(heading: float, pitch: float, roll: float, temperature: float,
                field_mg: tuple[float, float, float] | None = None) -> bytes:
    """One OS5000 output line ``$C<h>P<p>R<r>T<t>[Mx<x>My<y>Mz<z>]*HH`` CR LF (degrees, degrees C, one decimal;
    the field in mG with two)."""
    body = f"C{one_decimal(heading)}P{one_decimal(pitch)}R{one_decimal(roll)}T{one_decimal(temperature)}"
    if field_mg is not None:
        body += "".join(f"M{axis}{value:.2f}" for axis, value in zip("xyz", field_mg))
    return f"${body}*{calc_checksum(body)}\r\n".encode("ascii")


class Os5000CompassDevice(_CompassBase):
    """A mock OceanServer OS5000 tilt-compensated compass at *link_path* (its "$C" ASCII output)."""

    PROTOCOL: ClassVar[str] = "os5000"
    """What it speaks: the mock catalog refuses it for a driver whose declared ``protocol`` differs."""

    def __init__(self, vehicle: SimVehicle, *, link_path: str | os.PathLike[str], rate_hz: float = 10.0,
                 declination_deg: float = 0.0, heading_sigma_deg: float = 0.5, attitude_sigma_deg: float = 0.2,
                 temperature_c: float = 25.0, seed: int = 0, name: str = "compass", raw_field: bool = False,
                 earth_field_mg: tuple[float, float, float] = (200.0, 0.0, 450.0),
                 hard_iron_mg: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 soft_iron: tuple[tuple[float, float, float], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0),
                                                                      (0.0, 0.0, 1.0)),
                 field_noise_mg: float = 2.0) -> None:
        super().__init__(vehicle, link_path=link_path, rate_hz=rate_hz, name=name, declination_deg=declination_deg,
                         heading_sigma_deg=heading_sigma_deg, attitude_sigma_deg=attitude_sigma_deg, seed=seed)
        self.temperature_c = float(temperature_c)
        self.raw_field = raw_field
        self.earth_field_mg, self.hard_iron_mg, self.soft_iron = earth_field_mg, hard_iron_mg, soft_iron
        self.field_noise_mg = field_noise_mg

    def epoch_lines(self, truth: VehicleTruth) -> list[bytes]:
        """One ``$C...`` line for this epoch."""
        magnetic, pitch, roll = self.measure(truth)
        return [os5000_line(magnetic, pitch, roll, self.temperature_c, self._field(truth) if self.raw_field else None)]

    def _field(self, truth: VehicleTruth) -> tuple[float, float, float]:
        from u2sa_hw.mocks.mpu9250_chip import ned_to_body

        body = ned_to_body(self.earth_field_mg, truth.roll, truth.pitch, truth.yaw)
        return tuple(b + sum(k * f for k, f in zip(row, body)) + self.rng.gauss(0.0, self.field_noise_mg)
                     for row, b in zip(self.soft_iron, self.hard_iron_mg))  # type: ignore[return-value]
