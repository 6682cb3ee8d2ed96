"""A compass on a serial port: NMEA 0183 heading/attitude sentences or the OceanServer OS5000 ``$C`` format.

Publishes psi (true heading, rad in [-pi, pi), clockwise from north) and, when the device
reports them, phi (roll), theta (pitch) and psi_dot (rate of turn), each with its
configured sigma (or the device's own accuracy, PASHR).

Magnetic to true (east positive, as on charts)::

    magnetic = sensor heading + deviation      (HDG's deviation field; 0 when empty)
    true     = magnetic + declination          (declination_deg, or HDG's variation field
                                                when use_hdg_variation and it is present)

``format = "nmea"``: the sentences of drivers/compass/sentences.py (HDG, HDM, HDT, THS,
ROT, XDR pitch/roll/heel/trim, PASHR, PTNTHTM, PTNTHPR), grouped into bursts by sentence
order and time (drivers/compass/bursts.py); each burst is one message (one per sentence while
the device's burst order is being learned: never a heading with another burst's attitude).
Silence and burst timing are judged on the line's idle time, less each line's own time on the
wire at the address's baud rate and framing (a 25-character line takes 52 ms at 4800 8N1).
``format = "os5000"``: every ``$C`` line is one message (``u2sa_hw.drivers.compass.os5000_format``).
Every value is checked against its physical range and the configured device range
(``pitch_range_deg``, ``roll_range_deg``) before it is published; an impossible value is
dropped, counted per kind in health (``out_of_range_kinds``) and logged once.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

from u2sa_hw import lcmtypes as t
from u2sa_hw.config.fields import field
from u2sa_hw.geo import wrap_angle
from u2sa_hw.ports.declared import SOURCES

from u2sa_hw.drivers.compass import mag as compass_mag
from u2sa_hw.drivers.compass.bursts import Burst, BurstGrouper, CompassReading, reading_from_parts
from u2sa_hw.drivers.compass.sentences import AttitudeLimits, parse_compass_line
from u2sa_hw.drivers.nmea_fields import BadChecksum, SentenceError, is_foreign
from u2sa_hw.drivers.compass.os5000_format import OS5000_RANGES, Os5000BadChecksum, Os5000Error, is_os5000_line, parse_os5000
from u2sa_hw.drivers.serial_sensor import SerialLineSensor
from u2sa_hw.ports.address import AddressError
from u2sa_hw.drivers.value_ranges import ValueDrops

FORMATS = ("nmea", "os5000")


FACTORY_BAUD = 19200   # the OS5000's factory rate: a character's time before the device has an address


def char_time_s(*, baud: int, bytesize: int = 8, parity: str = "N", stopbits: float = 1.0) -> float:
    """How long one character takes on the wire (s): a start bit, the data bits, a parity bit unless
    *parity* is N, and the stop bits, at *baud* (10 bits at 4800 baud 8N1: 2.08 ms)."""
    return (1 + bytesize + (parity.upper() != "N") + stopbits) / baud


def state_from_reading(reading: CompassReading, *, heading_sigma_deg: float, attitude_sigma_deg: float,
                       rate_sigma_deg_s: float = 1.0) -> t.StateInformation | None:
    """psi, phi, theta, psi_dot in radians with their sigmas; None when the reading has none of them
    (or any value is not finite: never published)."""
    values = (reading.true_heading, reading.roll, reading.pitch, reading.rate_deg_s)
    if any(v is not None and not math.isfinite(v) for v in values):
        return None
    msg = t.StateInformation()
    msg.reference_frame = "NED"
    if reading.true_heading is not None:
        msg.set(psi=wrap_angle(math.radians(reading.true_heading)),
                psi_sigma=math.radians(reading.heading_sigma or heading_sigma_deg))
    if reading.roll is not None:
        msg.set(phi=math.radians(reading.roll), phi_sigma=math.radians(reading.roll_sigma or attitude_sigma_deg))
    if reading.pitch is not None:
        msg.set(theta=math.radians(reading.pitch),
                theta_sigma=math.radians(reading.pitch_sigma or attitude_sigma_deg))
    if reading.rate_deg_s is not None:
        msg.set(psi_dot=math.radians(reading.rate_deg_s), psi_dot_sigma=math.radians(rate_sigma_deg_s))
    return msg if msg.presence_vector else None


class SerialCompassDriver(SerialLineSensor):
    """A serial compass (NMEA heading/attitude sentences or an OceanServer OS5000) as a proprioceptive sensor."""

    EXAMPLE_PORT = "/dev/u2sa/compass"
    MOCK_KINDS = ("nmea_compass", "os5000_compass")
    CONFIG = (
        field("format", "nmea", "nmea: HDG/HDM/HDT/THS, ROT, XDR, PASHR, PTNTHTM/HPR; os5000: OceanServer $C lines "
                                "(any case)", choices=FORMATS, case_insensitive=True),
        field("declination_deg", 0.0, "magnetic declination, east positive: true = magnetic + declination", ge=-180, le=180),
        field("use_hdg_variation", True, "nmea: use HDG's variation field instead of declination_deg when present"),
        field("heading_sigma_deg", 1.0, "sigma of psi (deg)", gt=0, le=180),
        field("attitude_sigma_deg", 0.5, "sigma of phi and theta (deg)", gt=0, le=180),
        field("rate_sigma_deg_s", 1.0, "sigma of psi_dot from ROT (deg/s)", gt=0, le=1000),
        field("pitch_range_deg", 90.0, "the device's pitch range (deg, > 0 and <= 90): |pitch| beyond it is "
                                       "dropped (OS5000 90, HMR3300 60, HMR3000 40)", gt=0, le=90),
        field("roll_range_deg", 180.0, "the device's roll range (deg, > 0 and <= 180): |roll| beyond it is "
                                       "dropped (OS5000 180, HMR3300 60, HMR3000 40)", gt=0, le=180),
        *compass_mag.CONFIG,   # os5000 raw_field: heading from the corrected Mx/My/Mz (drivers/compass/mag.py)
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.bursts = self._new_grouper()
        self.reading: CompassReading | None = None
        self.out_of_range = ValueDrops(self.logger, device=self.device_name, what="out-of-range")
        self.not_valid = ValueDrops(self.logger, device=self.device_name, what="not-valid (by their status)")
        self.field_heading = compass_mag.CompassFieldHeading(self)

    @classmethod
    def protocol(cls, config: Mapping[str, Any]) -> str:
        """``format``: nmea or os5000."""
        return str(config.get("format", "nmea")).lower()

    @classmethod
    def mock_wiring(cls, service: str, device: str, config: Mapping[str, Any]) -> dict[str, Any]:
        """The protocol, from ``format`` (u2sa_hw/ports/declared.py)."""
        return {**super().mock_wiring(service, device, config), SOURCES: {"protocol": "format"}}

    def _new_grouper(self) -> BurstGrouper:
        return BurstGrouper(gap_s=self.config.get("epoch_gap_s"), char_time_s=self.char_time_s())

    def char_time_s(self) -> float:
        """One character's time on the wire at the device address's baud rate and framing (without an
        address, offline in ``u2sa check``: at the OS5000's factory 19200 8N1)."""
        address = self._link.address
        if address is None:
            try:
                address = self._link.resolve()
            except AddressError:
                return char_time_s(baud=FACTORY_BAUD)
        return char_time_s(baud=address.baud, bytesize=address.bytesize, parity=address.parity,
                           stopbits=address.stopbits)

    def check_config(self) -> None:
        """The serial checks, plus the calibration (mag_offset with mag_matrix); the fields' own rules are declared."""
        super().check_config()
        compass_mag.CompassFieldHeading(self).load()   # checked only: this also runs with a value being tried

    def setup(self) -> None:
        """The serial set-up, then the field calibration."""
        super().setup()
        self.field_heading.load()

    def on_config_change(self, name: str, value: Any) -> None:
        """The serial fields reopen the port (which also starts burst learning afresh)."""
        super().on_config_change(name, value)
        self.field_heading.on_config_change(name, value)
        if name in ("epoch_gap_s", "device"):   # a new device: its address's baud rate
            self.bursts = self._new_grouper()

    @property
    def format(self) -> str:
        """``"nmea"`` or ``"os5000"``."""
        return self.config.get("format")

    @property
    def limits(self) -> AttitudeLimits:
        """The configured pitch and roll ranges."""
        return AttitudeLimits(pitch_deg=self.config.get("pitch_range_deg"), roll_deg=self.config.get("roll_range_deg"))

    # -- lines ---------------------------------------------------------------------------------
    def handle_line(self, line: bytes, received: float) -> None:
        """Parse one line in the configured format."""
        if self.format == "os5000":
            self._os5000_line(line, received)
        else:
            self._nmea_line(line, received)

    def _os5000_line(self, line: bytes, received: float) -> None:
        if not is_os5000_line(line):
            if is_foreign(line) or (b"$" in line and line.rstrip().rfind(b"*") > line.rfind(b"$")):
                self.ignored += 1  # blank, AIS, or another sentence (the compass can also send $OHPR, $HCHDT)
            else:
                self.count_malformed(f"not a $C sentence: {line[:60]!r}")
            return
        try:
            os5000, noise = parse_os5000(line)
        except Os5000BadChecksum as exc:
            self.count_bad_checksum("$C", str(exc))
            return
        except Os5000Error as exc:
            self.count_malformed(str(exc))
            return
        self.count_valid(noise_bytes=noise)
        check, limits = self.out_of_range.check, self.limits
        heading = check("heading", os5000.heading, *OS5000_RANGES["heading"], unit=" deg")
        pitch_max, roll_max = min(limits.pitch_deg, OS5000_RANGES["pitch"][1]), min(limits.roll_deg,
                                                                                     OS5000_RANGES["roll"][1])
        from_field = self.field_heading.heading(os5000, pitch=os5000.pitch, roll=os5000.roll)
        if from_field is not None:
            heading = from_field
        self._publish(CompassReading(
            ("$C field" if from_field is not None else "$C") if heading is not None else "",
            true_heading=None if heading is None else heading + self.config.get("declination_deg"),
            magnetic_heading=heading, pitch=check("pitch", os5000.pitch, -pitch_max, pitch_max, unit=" deg"),
            roll=check("roll", os5000.roll, -roll_max, roll_max, unit=" deg"),
            temperature=check("temperature", os5000.temperature, *OS5000_RANGES["temperature"], unit=" C")),
            received)

    def _nmea_line(self, line: bytes, received: float) -> None:
        try:
            part = parse_compass_line(line, limits=self.limits, drops=self.out_of_range, not_valid=self.not_valid)
        except BadChecksum as exc:
            self.count_bad_checksum(exc.kind, str(exc))
            done = self.bursts.dropped(exc.kind)
            if done is not None:
                self._publish_burst(done)
            return
        except SentenceError as exc:
            self.count_malformed(str(exc))
            return
        if part is None:
            self.ignored += 1
            return
        self.count_valid(noise_bytes=part.noise_bytes)
        self.bursts.char_time_s = self.char_time_s()   # the address (and so its baud) may have changed
        for burst in self.bursts.add(part, received=received, chars=len(line)):
            self._publish_burst(burst)

    def handle_idle(self) -> None:
        """The line went quiet: the end of an NMEA burst."""
        done = self.bursts.flush()
        if done is not None:
            self._publish_burst(done)

    def on_port_lost(self) -> None:
        """Drop a half-received burst and what was learned about the device's bursts."""
        self.bursts.reset()

    def _publish_burst(self, burst: Burst) -> None:
        for piece in burst.pieces():   # one per sentence while the burst order is not known
            reading = reading_from_parts(piece.parts, declination_deg=self.config.get("declination_deg"),
                                         use_hdg_variation=self.config.get("use_hdg_variation"))
            self._publish(reading, piece.received)

    def _publish(self, reading: CompassReading, received: float) -> None:
        msg = state_from_reading(reading, heading_sigma_deg=self.config.get("heading_sigma_deg"),
                                 attitude_sigma_deg=self.config.get("attitude_sigma_deg"),
                                 rate_sigma_deg_s=self.config.get("rate_sigma_deg_s"))
        if msg is None:
            self.ignored += 1
            return
        self.reading = reading
        self.publish_measurement(msg, received=received)

    # -- health ----------------------------------------------------------------------------------
    def sensor_details(self) -> dict[str, Any]:
        """The latest heading (true and magnetic), pitch, roll, rate of turn and temperature, in degrees;
        dropped values by kind; how bursts are grouped."""
        r = self.reading
        details: dict[str, Any] = {"format": self.format, "declination_deg": self.config.get("declination_deg"),
                                   **self.out_of_range.details("out_of_range"),
                                   **self.not_valid.details("not_valid"), **self.field_heading.details()}
        if self.format == "nmea":
            details["burst_rule"] = self.bursts.rule
        if r is not None:
            details.update({
                "source": r.source,
                "heading_deg": _deg360(r.true_heading),
                "magnetic_heading_deg": _deg360(r.magnetic_heading),
                "pitch_deg": _one(r.pitch),
                "roll_deg": _one(r.roll),
                "rate_of_turn_deg_s": _one(r.rate_deg_s),
                "heading_mode": r.mode,
                "temperature_c": _one(r.temperature),
            })
        return details


def _deg360(value: float | None) -> str:
    return "" if value is None else f"{value % 360.0:.1f}"


def _one(value: float | None) -> str:
    return "" if value is None else f"{value:.1f}"
