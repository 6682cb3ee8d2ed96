"""A compass on a serial port: NMEA 0183 HDG/HDM/HDT (+ XDR pitch/roll) or the OceanServer OS5000 ``$C`` format.

Publishes psi (true heading, rad in [-pi, pi), clockwise from north) and, when the device
reports them, phi (roll) and theta (pitch), each with its configured sigma.

Magnetic to true (east positive, as on charts)::

    magnetic = sensor heading + deviation      (HDG's deviation field; 0 when empty)
    true     = magnetic + declination          (declination_deg, or HDG's variation field
                                                when use_hdg_variation and it is present)

``format = "nmea"``: sentences are grouped into bursts (a repeated heading sentence or
``epoch_gap_s`` of silence ends one) and each burst is one message; when a burst has more
than one heading sentence, HDT wins over HDG over HDM. XDR angle transducers named
``PITCH``/``PTCH`` and ``ROLL`` in degrees give theta and phi.
``format = "os5000"``: every ``$C`` line is one message (``drivers.os5000_format``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from u2sa_hw import lcmtypes as t
from u2sa_hw.config import ConfigError, field
from u2sa_hw.geo import wrap_angle

from drivers.nmea_fields import BadChecksum, Epoch, EpochCollector, SentenceError, number, parse_sentence, signed, text
from drivers.os5000_format import Os5000BadChecksum, Os5000Error, is_os5000_line, parse_os5000
from drivers.serial_sensor import SerialLineSensor

FORMATS = ("nmea", "os5000")
HEADING_KINDS = ("HDT", "HDG", "HDM")  # preference order within one burst
COMPASS_KINDS = frozenset({*HEADING_KINDS, "XDR"})
PITCH_IDS = frozenset({"PITCH", "PTCH"})
ROLL_IDS = frozenset({"ROLL"})


@dataclass(frozen=True)
class CompassReading:
    """One measurement in degrees: true and magnetic heading, pitch, roll (None when not reported)."""

    source: str                       # "HDT", "HDG", "HDM", "$C" or "" (attitude only)
    true_heading: float | None = None
    magnetic_heading: float | None = None
    pitch: float | None = None
    roll: float | None = None
    temperature: float | None = None


def xdr_attitude(msgs: list[Any]) -> tuple[float | None, float | None]:
    """(pitch, roll) in degrees from XDR angle transducers named PITCH/PTCH and ROLL."""
    pitch = roll = None
    for msg in msgs:
        n = 1
        while hasattr(msg, f"tdrid_{n:02d}"):
            ident = text(msg, f"tdrid_{n:02d}").upper()
            unit = text(msg, f"dataunit_{n:02d}").upper()
            value = number(msg, f"data_{n:02d}")
            if value is not None and unit in ("D", ""):
                if ident in PITCH_IDS:
                    pitch = value
                elif ident in ROLL_IDS:
                    roll = value
            n += 1
    return pitch, roll


def reading_from_epoch(epoch: Epoch, *, declination_deg: float, use_hdg_variation: bool) -> CompassReading:
    """The heading, pitch and roll one NMEA burst says (see the module docstring for the rules)."""
    pitch, roll = xdr_attitude(epoch.all("XDR"))
    for kind in HEADING_KINDS:
        msg = epoch.first(kind)
        if msg is None:
            continue
        if kind == "HDT":
            heading = number(msg, "headingT")
            if heading is not None:
                return CompassReading("HDT", true_heading=heading, pitch=pitch, roll=roll)
            continue
        sensor = number(msg, "headingM")
        if sensor is None:
            continue
        declination = declination_deg
        if kind == "HDG":
            sensor += signed(number(msg, "deviation"), text(msg, "deviationEW")) or 0.0
            variation = signed(number(msg, "variation"), text(msg, "variationEW"))
            if use_hdg_variation and variation is not None:
                declination = variation
        return CompassReading(kind, true_heading=sensor + declination, magnetic_heading=sensor, pitch=pitch, roll=roll)
    return CompassReading("", pitch=pitch, roll=roll)


def state_from_reading(reading: CompassReading, *, heading_sigma_deg: float,
                       attitude_sigma_deg: float) -> t.StateInformation | None:
    """psi (and phi, theta) in radians with their sigmas; None when the reading has none of them."""
    msg = t.StateInformation()
    msg.reference_frame = "NED"
    if reading.true_heading is not None:
        msg.set(psi=wrap_angle(math.radians(reading.true_heading)), psi_sigma=math.radians(heading_sigma_deg))
    attitude_sigma = math.radians(attitude_sigma_deg)
    if reading.roll is not None:
        msg.set(phi=math.radians(reading.roll), phi_sigma=attitude_sigma)
    if reading.pitch is not None:
        msg.set(theta=math.radians(reading.pitch), theta_sigma=attitude_sigma)
    return msg if msg.presence_vector else None


class SerialCompassDriver(SerialLineSensor):
    """A serial compass (NMEA heading sentences or an OceanServer OS5000) as a proprioceptive sensor."""

    EXAMPLE_PORT = "/dev/u2sa/compass"
    CONFIG = (
        field("baudrate", 19200, "one of 4800 .. 115200 (19200: the OS5000's factory rate; NMEA compasses often 4800)"),
        field("format", "nmea", "nmea: HDG/HDM/HDT (+ XDR pitch/roll); os5000: OceanServer $C sentences"),
        field("declination_deg", 0.0, "magnetic declination, east positive: true = magnetic + declination"),
        field("use_hdg_variation", True, "nmea: use HDG's variation field instead of declination_deg when present"),
        field("heading_sigma_deg", 1.0, "sigma of psi (deg)"),
        field("attitude_sigma_deg", 0.5, "sigma of phi and theta (deg)"),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.epochs = EpochCollector()
        self.reading: CompassReading | None = None

    def check_config(self) -> None:
        """The serial fields, plus the format, declination and sigmas."""
        super().check_config()
        cfg = self.config
        if cfg.get("format").lower() not in FORMATS:
            raise ConfigError(f"service '{self.name}': format {cfg.get('format')!r} is not one of {', '.join(FORMATS)}")
        if not -180.0 <= cfg.get("declination_deg") <= 180.0:
            raise ConfigError(f"service '{self.name}': declination_deg must be within -180..180 (east positive), "
                              f"got {cfg.get('declination_deg')!r}")
        for key in ("heading_sigma_deg", "attitude_sigma_deg"):
            if not cfg.get(key) > 0:
                raise ConfigError(f"service '{self.name}': {key} must be > 0, got {cfg.get(key)!r}")

    @property
    def format(self) -> str:
        """``"nmea"`` or ``"os5000"``."""
        return self.config.get("format").lower()

    # -- lines ---------------------------------------------------------------------------------
    def handle_line(self, line: bytes, received: float) -> None:
        """Parse one line in the configured format."""
        if self.format == "os5000":
            self._os5000_line(line, received)
        else:
            self._nmea_line(line, received)

    def _os5000_line(self, line: bytes, received: float) -> None:
        if not is_os5000_line(line):
            if b"$" in line and line.rstrip().rfind(b"*") > line.rfind(b"$"):
                self.ignored += 1  # another sentence (the compass can also send $OHPR, $HCHDT)
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
        self._publish(CompassReading("$C", true_heading=os5000.heading + self.config.get("declination_deg"),
                                     magnetic_heading=os5000.heading, pitch=os5000.pitch, roll=os5000.roll,
                                     temperature=os5000.temperature), received)

    def _nmea_line(self, line: bytes, received: float) -> None:
        try:
            sentence = parse_sentence(line)
        except BadChecksum as exc:
            self.count_bad_checksum(exc.kind, str(exc))
            done = self.epochs.dropped(exc.kind)
            if done is not None:
                self._publish_epoch(done)
            return
        except SentenceError as exc:
            self.count_malformed(str(exc))
            return
        if sentence is None or sentence.kind not in COMPASS_KINDS:
            self.ignored += 1
            return
        self.count_valid(noise_bytes=sentence.noise_bytes)
        done = self.epochs.add(sentence, received=received)
        if done is not None:
            self._publish_epoch(done)

    def handle_idle(self) -> None:
        """The end of an NMEA burst."""
        done = self.epochs.flush()
        if done is not None:
            self._publish_epoch(done)

    def on_port_lost(self) -> None:
        """Drop a half-received burst."""
        self.epochs.flush()

    def _publish_epoch(self, epoch: Epoch) -> None:
        reading = reading_from_epoch(epoch, declination_deg=self.config.get("declination_deg"),
                                     use_hdg_variation=self.config.get("use_hdg_variation"))
        self._publish(reading, epoch.received)

    def _publish(self, reading: CompassReading, received: float) -> None:
        msg = state_from_reading(reading, heading_sigma_deg=self.config.get("heading_sigma_deg"),
                                 attitude_sigma_deg=self.config.get("attitude_sigma_deg"))
        if msg is None:
            self.ignored += 1
            return
        self.reading = reading
        self.publish_measurement(msg, received=received)

    # -- health ----------------------------------------------------------------------------------
    def sensor_details(self) -> dict[str, Any]:
        """The latest heading (true and magnetic), pitch, roll and temperature, in degrees."""
        r = self.reading
        details: dict[str, Any] = {"format": self.format, "declination_deg": self.config.get("declination_deg")}
        if r is not None:
            details.update({
                "source": r.source,
                "heading_deg": _deg360(r.true_heading),
                "magnetic_heading_deg": _deg360(r.magnetic_heading),
                "pitch_deg": "" if r.pitch is None else f"{r.pitch:.1f}",
                "roll_deg": "" if r.roll is None else f"{r.roll:.1f}",
                "temperature_c": "" if r.temperature is None else f"{r.temperature:.1f}",
            })
        return details


def _deg360(value: float | None) -> str:
    return "" if value is None else f"{value % 360.0:.1f}"
