"""NMEA 0183 GNSS sentences and whole receiver streams, composed here from the sentence definitions.

Every sentence is built field by field as NMEA 0183 (2.3 to 4.11) defines it and its
checksum computed (XOR of the characters between ``$`` and ``*``). A :class:`Receiver`
describes one receiver's output: talkers, sentence order, per-sentence rates, decimals and
its quirks; :func:`stream` turns a trajectory into the timed lines a driver reads, with a
modelled wire (each line arrives when its last byte has at the baud rate; a pause of
``GAP_S`` or more is reported as silence, as the driver's read timeout does).
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass, field, replace
from typing import Callable, Iterator

from u2sa_hw.drivers.gps_nmea.driver import GpsNmeaDriver
from u2sa_hw.drivers.nmea_fields import Epoch, parse_sentence
from u2sa_hw import lcmtypes as t
from u2sa_hw.geo import ned_to_geodetic
from u2sa_hw.profile.vehicle import Origin, VehicleProfile

KNOT_MPS = 1852.0 / 3600.0
GAP_S = 0.05
START = dt.datetime(2026, 3, 14, 23, 59, 0, tzinfo=dt.timezone.utc)   # crosses midnight a minute in


def checksum(body: str) -> str:
    """The two hex digits of an NMEA checksum of *body* (between ``$`` and ``*``)."""
    value = 0
    for char in body.encode("ascii"):
        value ^= char
    return f"{value:02X}"


def nmea(body: str) -> bytes:
    """``$<body>*HH`` CR LF."""
    return f"${body}*{checksum(body)}\r\n".encode("ascii")


def dm(value: float, *, lat: bool, decimals: int = 5) -> tuple[str, str]:
    """Degrees to ``ddmm.mmmmm`` / ``dddmm.mmmmm`` with *decimals* in the minutes, and the hemisphere."""
    scaled = round(abs(value) * 60.0 * 10 ** decimals)
    deg, minutes = divmod(scaled, 60 * 10 ** decimals)
    whole, frac = divmod(minutes, 10 ** decimals)
    text = f"{deg:02d}" if lat else f"{deg:03d}"
    text += f"{whole:02d}" + (f".{frac:0{decimals}d}" if decimals else "")
    return text, ("N" if value >= 0 else "S") if lat else ("E" if value >= 0 else "W")


def printed(value: float, *, decimals: int = 5) -> float:
    """*value* (degrees) as a receiver printing *decimals* in the minutes gives it."""
    step = 10.0 ** decimals * 60.0
    return math.copysign(round(abs(value) * step) / step, value)


def hhmmss(when: dt.datetime, decimals: int = 2) -> str:
    """UTC time of day as ``hhmmss.ss``."""
    text = when.strftime("%H%M%S")
    if decimals:
        text += f"{when.microsecond / 1e6:.{decimals}f}"[1:]
    return text


@dataclass(frozen=True)
class Solution:
    """One epoch's solution, as the receiver reports it."""

    when: dt.datetime
    lat: float
    lon: float
    alt: float = 12.0             # MSL
    sep: float = -30.5            # geoid separation
    speed: float = 0.0            # m/s
    course: float | None = 0.0    # degrees true; None: the receiver leaves it empty
    heading: float = 0.0          # HDT
    sats: int = 9
    hdop: float = 0.9
    vdop: float = 1.4
    quality: int = 1


def gga(s: Solution, *, talker: str = "GP", decimals: int = 5, sep: bool = True, alt: bool = True,
        quality: int | None = None, sats: str | None = None) -> bytes:
    la, ns = dm(s.lat, lat=True, decimals=decimals)
    lo, ew = dm(s.lon, lat=False, decimals=decimals)
    q = s.quality if quality is None else quality
    used = f"{s.sats:02d}" if sats is None else sats
    altitude = f"{s.alt:.2f}" if alt else ""
    separation = f"{s.sep:.1f}" if sep else ""
    return nmea(f"{talker}GGA,{hhmmss(s.when)},{la},{ns},{lo},{ew},{q},{used},{s.hdop:.2f},{altitude},M,"
                f"{separation},M,,")


def rmc(s: Solution, *, talker: str = "GP", decimals: int = 5, status: str = "A", mode: str = "A") -> bytes:
    la, ns = dm(s.lat, lat=True, decimals=decimals)
    lo, ew = dm(s.lon, lat=False, decimals=decimals)
    course = "" if s.course is None else f"{s.course:.2f}"
    return nmea(f"{talker}RMC,{hhmmss(s.when)},{status},{la},{ns},{lo},{ew},{s.speed / KNOT_MPS:.3f},{course},"
                f"{s.when.strftime('%d%m%y')},,,{mode}")


def gll(s: Solution, *, talker: str = "GP", decimals: int = 4, status: str = "A", mode: str = "A") -> bytes:
    la, ns = dm(s.lat, lat=True, decimals=decimals)
    lo, ew = dm(s.lon, lat=False, decimals=decimals)
    return nmea(f"{talker}GLL,{la},{ns},{lo},{ew},{hhmmss(s.when)},{status},{mode}")


def gns(s: Solution, *, talker: str = "GN", modes: str = "AA", decimals: int = 5) -> bytes:
    la, ns = dm(s.lat, lat=True, decimals=decimals)
    lo, ew = dm(s.lon, lat=False, decimals=decimals)
    return nmea(f"{talker}GNS,{hhmmss(s.when)},{la},{ns},{lo},{ew},{modes},{s.sats:02d},{s.hdop:.2f},{s.alt:.2f},"
                f"{s.sep:.1f},,,V")


def vtg(s: Solution, *, talker: str = "GP", mode: str = "A") -> bytes:
    course = "" if s.course is None else f"{s.course:.2f}"
    return nmea(f"{talker}VTG,{course},T,,M,{s.speed / KNOT_MPS:.3f},N,{s.speed * 3.6:.3f},K,{mode}")


def gsa(s: Solution, *, talker: str = "GP", mode: int = 3, prns: tuple[int, ...] = (2, 5, 7, 9, 13, 15)) -> bytes:
    used = [f"{p:02d}" for p in prns][:12]
    used += [""] * (12 - len(used))
    pdop = math.hypot(s.hdop, s.vdop)
    return nmea(f"{talker}GSA,A,{mode},{','.join(used)},{pdop:.2f},{s.hdop:.2f},{s.vdop:.2f}")


def gst(s: Solution, *, talker: str = "GP", sigma: float = 0.8, vsigma: float = 1.6) -> bytes:
    return nmea(f"{talker}GST,{hhmmss(s.when)},1.0,{sigma:.2f},{sigma:.2f},0.0,{sigma:.2f},{sigma:.2f},{vsigma:.2f}")


def zda(s: Solution, *, talker: str = "GP") -> bytes:
    w = s.when
    return nmea(f"{talker}ZDA,{hhmmss(w)},{w.day:02d},{w.month:02d},{w.year:04d},00,00")


def hdt(s: Solution, *, talker: str = "GP") -> bytes:
    return nmea(f"{talker}HDT,{s.heading:.2f},T")


BUILDERS: dict[str, Callable[..., bytes]] = {"GGA": gga, "RMC": rmc, "GLL": gll, "GNS": gns, "VTG": vtg,
                                             "GSA": gsa, "GST": gst, "ZDA": zda, "HDT": hdt}


@dataclass(frozen=True)
class Part:
    """One sentence of a receiver's epoch: *kind* from *talker*, every *every*-th epoch, with builder options."""

    kind: str
    talker: str = "GP"
    every: int = 1
    options: dict[str, object] = field(default_factory=dict)
    pause_before_s: float = 0.0    # the receiver pauses this long before sending it (a late heading engine)


@dataclass(frozen=True)
class Receiver:
    """A receiver's output: its epoch's parts in order, rate, baud, and quirks."""

    parts: tuple[Part, ...]
    rate_hz: float = 1.0
    baud: int = 9600
    extra_lines: tuple[bytes, ...] = ()   # sent after each epoch (blank lines, AIS sharing the port)


def trajectory(origin: Origin, k: int, rate_hz: float, *, stop_every_s: float = 40.0) -> Solution:
    """Epoch *k* of a rover driving a 60 m circle about *origin* at 2 m/s, standing still 5 s
    every *stop_every_s* (speed 0 and the course left empty then, as receivers do at rest)."""
    when = START + dt.timedelta(seconds=k / rate_hz)
    t_s = k / rate_hz
    standing = (t_s % stop_every_s) >= stop_every_s - 5.0
    moving_s = t_s - 5.0 * (t_s // stop_every_s) - (((t_s % stop_every_s) - (stop_every_s - 5.0))
                                                    if standing else 0.0)
    radius, speed = 60.0, 2.0
    angle = moving_s * speed / radius
    north, east = radius * math.sin(angle), radius * (1.0 - math.cos(angle))
    lat, lon, _ = ned_to_geodetic(north, east, 0.0, origin=origin)
    course = (math.degrees(angle) % 360.0)
    return Solution(when=when, lat=lat, lon=lon, alt=12.0 + 0.01 * k % 3, speed=0.0 if standing else speed,
                    course=None if standing else course, heading=(course + 3.0) % 360.0)


def epoch_lines(receiver: Receiver, sol: Solution, k: int) -> list[tuple[float, bytes]]:
    """(pause before, line) for epoch *k*."""
    out = []
    for part in receiver.parts:
        if k % part.every:
            continue
        out.append((part.pause_before_s, BUILDERS[part.kind](sol, talker=part.talker, **part.options)))
    out.extend((0.0, line) for line in receiver.extra_lines)
    return out


def stream(receiver: Receiver, solutions: Callable[[int], Solution], epochs: int,
           *, edit: Callable[[int, list[tuple[float, bytes]]], list[tuple[float, bytes]]] | None = None
           ) -> Iterator[tuple[float, bytes | None]]:
    """(arrival time, line) as the driver reads them; (time, None) where its read timeout reports silence.

    *edit* may change each epoch's (pause, line) list (drop, duplicate or corrupt a sentence).
    """
    last: float | None = None
    clock = 0.0
    for k in range(epochs):
        clock = max(clock, k / receiver.rate_hz)
        lines = epoch_lines(receiver, solutions(k), k)
        if edit is not None:
            lines = edit(k, lines)
        for pause, line in lines:
            clock += pause                     # the line's first byte goes out now
            if last is not None and clock - last >= GAP_S:
                yield last + GAP_S, None       # the read timeout: no byte for GAP_S
            clock += len(line) * 10.0 / receiver.baud
            yield clock, line
            last = clock


def with_time(sol: Solution, seconds: float) -> Solution:
    """*sol* stamped *seconds* later."""
    return replace(sol, when=sol.when + dt.timedelta(seconds=seconds))


def recording_driver(base: type) -> type:
    """*base* (a real sensor driver class) whose every published state is also kept in ``sent``."""

    class Recording(base):  # type: ignore[valid-type, misc]
        def __init__(self, *args: object, **kwargs: object) -> None:
            super().__init__(*args, **kwargs)
            self.sent: list[t.StateInformation] = []

        def publish_state(self, msg: t.StateInformation) -> bool:
            self.sent.append(msg)
            return super().publish_state(msg)

    Recording.__name__ = Recording.__qualname__ = f"Recording{base.__name__}"
    Recording.__doc__ = f"The real {base.__name__}; every message it publishes is also kept in ``sent``."
    return Recording


RecordingGps = recording_driver(GpsNmeaDriver)


def serial_profile(device: str = "gps", baud: int = 9600) -> VehicleProfile:
    """A profile (no file) whose *device* is ``/dev/u2sa/DEVICE`` at *baud*: a driver built on it opens nothing
    until its setup."""
    return VehicleProfile(path=None, devices={device: {"address": f"serial:///dev/u2sa/{device}?baud={baud}"}})


def epoch(*lines: bytes) -> Epoch:
    """One parsed epoch of *lines* (each must parse), received at 0."""
    e = Epoch(received=0.0)
    for line in lines:
        s = parse_sentence(line)
        assert s is not None, line
        e.sentences.append(s)
    return e
