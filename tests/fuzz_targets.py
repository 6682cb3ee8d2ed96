"""Fuzz targets for the parsers of tests/test_fuzz_*.py and bench/fuzz.py, and a seeded mutator.

A target takes one input (bytes) through the real driver code -- the compass driver's
``handle_line`` in NMEA and OS5000 format, the ODrive and VESC drivers' frame dispatch --
and raises when the input breaks a rule: an exception that escapes the parser (anything but
the drops the driver counts), or a published value that is not finite or outside its range.
:class:`Mutator` makes inputs from a corpus of valid ones (bit flips, interesting bytes and
numbers, long digit runs, splices, truncation; for NMEA, the checksum fixed afterwards most
of the time, so the fields are reached and not only the checksum check).
"""

from __future__ import annotations

import math
import random
import struct
from pathlib import Path
from typing import Any, Callable

import can
from pynmeagps.nmeahelpers import calc_checksum

from u2sa_hw.drivers.compass.driver import SerialCompassDriver
from u2sa_hw.drivers.can_motor.odrive.driver import OdriveCanMotor
from u2sa_hw.drivers.can_motor.vesc.driver import VescCanMotor
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.auth import OK, TRAILER_LEN
from u2sa_hw.messages import REGISTRY, MalformedMessage
from u2sa_hw.protocols import odrive_cansimple as cs
from u2sa_hw.protocols import vesc_can as vc
from u2sa_hw.bus.transport import Transport
from u2sa_hw.profile.vehicle import VehicleProfile


class FuzzViolation(AssertionError):
    """An input broke a rule: the message names the input and what was published."""


INTERESTING_TEXT = [b"", b"0", b"-", b".", b",", b"*", b"$", b"e", b"E", b"1e308", b"-1e308", b"nan", b"inf",
                    b"9" * 30, b"9" * 400, b"-" + b"9" * 24, b"0." + b"0" * 40 + b"1", b"360.0", b"-90.0", b"180.1",
                    b"\x00", b"\xff", b"\r", b",,,,", b"A", b"V", b"T", b"M", b"W", b"E", b"P", b"L"]
INTERESTING_FLOATS = [math.inf, -math.inf, math.nan, 3.4e38, -3.4e38, 1e30, 1e-45, -0.0, 0.0, 1.0, 100.0, 1e6]
INTERESTING_INTS = [0, 1, -1, 0x7FFFFFFF, -0x80000000, 0xFFFFFFFF, 0x7FFF, -0x8000, 0xFFFF, 255]


class Mutator:
    """Seeded mutations of corpus inputs (deterministic for one seed)."""

    def __init__(self, corpus: list[bytes], *, seed: int, nmea: bool = False) -> None:
        self.corpus = corpus
        self.rng = random.Random(seed)
        self.nmea = nmea

    def next(self) -> bytes:
        """One mutated input (1 to 4 mutations of a corpus entry)."""
        rng = self.rng
        data = bytearray(rng.choice(self.corpus))
        for _ in range(rng.randint(1, 4)):
            self._mutate(data)
        if self.nmea and rng.random() < 0.75:
            return fix_checksum(bytes(data))
        return bytes(data)

    def _mutate(self, data: bytearray) -> None:
        rng = self.rng
        op = rng.randrange(8)
        pos = rng.randrange(len(data) + 1)
        if op == 0 and data:
            data[min(pos, len(data) - 1)] ^= 1 << rng.randrange(8)
        elif op == 1:
            data[pos:pos] = rng.choice(INTERESTING_TEXT)
        elif op == 2 and data:   # replace a field (between commas) with something interesting
            fields = bytes(data).split(b",")
            fields[rng.randrange(len(fields))] = rng.choice(INTERESTING_TEXT)
            data[:] = b",".join(fields)
        elif op == 3:
            end = min(len(data), pos + rng.randint(1, 8))
            del data[pos:end]
        elif op == 4:
            other = rng.choice(self.corpus)
            cut = rng.randrange(len(other) + 1)
            data[pos:] = other[cut:]
        elif op == 5:
            del data[pos:]
        elif op == 6 and len(data) >= 4:   # an interesting float or int over 4 bytes
            at = rng.randrange(len(data) - 3)
            if rng.random() < 0.5:
                data[at:at + 4] = struct.pack(rng.choice("<>") + "f", rng.choice(INTERESTING_FLOATS))
            else:
                data[at:at + 4] = struct.pack(rng.choice("<>") + "I", rng.choice(INTERESTING_INTS) & 0xFFFFFFFF)
        else:
            data[pos:pos] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 4)))


def nmea(body: str) -> bytes:
    """``$body*HH`` CR LF with its checksum."""
    return f"${body}*{calc_checksum(body)}\r\n".encode()


def fix_checksum(line: bytes) -> bytes:
    """*line* with the checksum its text between the last ``$`` and ``*`` needs (as a device would send it)."""
    start = line.rfind(b"$")
    star = line.find(b"*", start + 1)
    if start < 0:
        return line
    body = line[start + 1:star if star > 0 else len(line)].rstrip(b"\r\n")
    try:
        checksum = calc_checksum(body.decode("latin-1")).encode()
    except (ValueError, UnicodeError):
        return line
    return line[:start] + b"$" + body + b"*" + checksum + b"\r\n"


COMPASS_CORPUS = [nmea(b) for b in (
    "HCHDG,98.3,1.5,W,12.6,W", "HCHDM,350.0,M", "HEHDT,30.0,T", "HETHS,316.70,E", "HEROT,-35.2,A",
    "HCXDR,A,-3.5,D,PITCH,A,12.0,D,ROLL", "IIXDR,A,4.0,D,HEEL,A,-1.0,D,TRIM", "HCXDR,A,1.0,D,PTCH",
    "PASHR,123456.00,45.50,T,1.20,-2.30,0.05,0.020,0.030,0.150,1,1", "PTNTHTM,285.2,N,-2.4,N,10.7,N,59.1,3844",
    "PTNTHPR,59.6,N,-0.2,N,-3.0,N", "PTNTHPR,,N,-1.5,N,,P", "GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,,,,")]
OS5000_CORPUS = [b"$C320.5P0.2R-18.3T19.0*3C\r\n",
                 b"$C212.4P2.5R-14.0T28.4Mx107977.90My-79422.00Mz173.27Ax0.045Ay-0.245Az0.977*3A\r\n",
                 nmea("C328.3P28.4R-12.4T21.1D21.01"), nmea("C7.0")]


class _Recording:
    """Mixin: keep every STATE_INFO message the service publishes in ``sent``."""

    sent: list[t.StateInformation]

    def publish(self, channel: str, msg: Any, **kwargs: Any) -> bool:
        if isinstance(msg, t.StateInformation):
            self.sent.append(msg)
        return super().publish(channel, msg, **kwargs)  # type: ignore[misc]


class RecordingCompass(_Recording, SerialCompassDriver):
    """The compass driver, its messages kept."""


class RecordingOdrive(_Recording, OdriveCanMotor):
    """The ODrive driver, its messages kept."""


class RecordingVesc(_Recording, VescCanMotor):
    """The VESC driver, its messages kept."""


def _finite(msg: t.StateInformation) -> list[str]:
    return [name for name in msg.present_fields() if not math.isfinite(getattr(msg, name))]


def check_compass_message(msg: t.StateInformation) -> None:
    """Every value finite and within the ranges the driver promises."""
    bad = _finite(msg)
    if msg.has("psi") and not -math.pi <= msg.psi < math.pi:
        bad.append(f"psi {msg.psi}")
    if msg.has("theta") and abs(msg.theta) > math.pi / 2:
        bad.append(f"theta {msg.theta}")
    if msg.has("phi") and abs(msg.phi) > math.pi:
        bad.append(f"phi {msg.phi}")
    if msg.has("psi_dot") and abs(msg.psi_dot) > math.radians(9999.9 / 60.0):
        bad.append(f"psi_dot {msg.psi_dot}")
    for name in ("psi_sigma", "theta_sigma", "phi_sigma", "psi_dot_sigma"):
        if msg.has(name) and not 0 < getattr(msg, name) <= math.pi:
            bad.append(f"{name} {getattr(msg, name)}")
    if bad:
        raise FuzzViolation(f"published {bad}")


def check_motion_message(msg: t.StateInformation, *, max_speed: float, track_width: float) -> None:
    """Odometry: finite, a body speed no wheel pair can exceed and the yaw rate that goes with it."""
    bad = _finite(msg)
    if msg.has("x_dot") and abs(msg.x_dot) > max_speed:
        bad.append(f"x_dot {msg.x_dot}")
    if msg.has("psi_dot") and abs(msg.psi_dot) > 2 * max_speed / track_width:
        bad.append(f"psi_dot {msg.psi_dot}")
    if bad:
        raise FuzzViolation(f"published {bad}")


class Target:
    """One parser under fuzz: ``run(data)`` feeds one input; ``close()`` releases the bus."""

    name = ""
    corpus: list[bytes] = []
    nmea = False

    def run(self, data: bytes) -> None:
        raise NotImplementedError

    def close(self) -> None:
        """Stop the transport."""


class CompassTarget(Target):
    """The compass driver's line handling in one format (``nmea`` or ``os5000``)."""

    def __init__(self, fmt: str, *, workdir: Path, lcm_url: str) -> None:
        self.name = f"compass-{fmt}"
        self.corpus = COMPASS_CORPUS if fmt == "nmea" else OS5000_CORPUS
        self.nmea = True
        self.transport = Transport(lcm_url, name=self.name)
        profile = VehicleProfile(path=None, devices={"compass": {"address": "serial:///dev/u2sa/compass?baud=19200"}})
        self.driver = RecordingCompass("compass", profile=profile, config_path=workdir / f"{self.name}.toml",
                                       transport=self.transport, settings={"format": fmt})
        self.driver.sent = []
        self.now = 1000.0

    def run(self, data: bytes) -> None:
        drv = self.driver
        self.now += 0.01
        try:
            drv.handle_line(data, self.now)
            if data[-1:] == b"\n" and len(data) % 3 == 0:
                drv.handle_idle()   # a silence now and then
        except Exception as exc:  # noqa: BLE001 - the point of the fuzz: nothing may escape
            raise FuzzViolation(f"{type(exc).__name__}: {exc} escaped the compass driver for {data!r}") from exc
        try:
            for msg in drv.sent:
                check_compass_message(msg)
        except FuzzViolation as exc:
            raise FuzzViolation(f"{exc} after {data!r}") from None
        finally:
            drv.sent.clear()

    def close(self) -> None:
        self.transport.stop()


def odrive_corpus() -> list[bytes]:
    """``id(2 bytes, LE) + data`` inputs: the frames an ODrive sends, for nodes 0 and 1."""
    out = []
    for node in (0, 1):
        for cmd, data in ((cs.Cmd.HEARTBEAT, cs.encode_heartbeat(cs.Heartbeat(0, 8))),
                          (cs.Cmd.GET_ENCODER_ESTIMATES, cs.encode_encoder_estimates(12.5, 1.5)),
                          (cs.Cmd.GET_ENCODER_ESTIMATES, cs.encode_encoder_estimates(-3.0, -0.5)),
                          (cs.Cmd.GET_BUS_VOLTAGE_CURRENT, cs.encode_bus_voltage_current(24.0, 1.2)),
                          (cs.Cmd.GET_ERROR, cs.encode_get_error(0, 0)),
                          (cs.Cmd.GET_TEMPERATURE, cs.encode_floats(40.0, 35.0)),
                          (cs.Cmd.GET_VERSION, cs.encode_version(cs.Version(2, 4, 4, 0, 0, 6, 10, 0))),
                          (cs.Cmd.TX_SDO, cs.encode_tx_sdo(10, "float", 0.3))):
            out.append(struct.pack("<H", cs.arbitration_id(node, cmd)) + data)
    return out


def vesc_corpus() -> list[bytes]:
    """``id(2 bytes, BE) + data`` inputs: STATUS 1-6 of controllers 0 and 1, COMM replies to host 254."""
    statuses = (vc.Status1(1200.0, 5.3, 0.456), vc.Status2(1.5, 0.1), vc.Status3(20.0, 1.0),
                vc.Status4(40.0, 35.0, 2.0, 90.0), vc.Status5(12345, 24.5), vc.Status6(1.0, 2.0, 3.0, 0.5))
    out = []
    for controller in (0, 1):
        for status in statuses:
            out.append(struct.pack(">H", vc.ext_id(vc.status_packet_id(status), controller))
                       + vc.encode_status(status))
    for frame in vc.buffer_frames(254, 1, bytes([vc.CommPacket.GET_APPCONF]) + bytes(range(40))):
        out.append(struct.pack(">H", frame.arbitration_id) + bytes(frame.data))
    return out


class CanTarget(Target):
    """A CAN motor driver's frame dispatch (decode errors are its counted drops)."""

    def __init__(self, kind: str, *, workdir: Path, lcm_url: str) -> None:
        self.name = kind
        self.transport = Transport(lcm_url, name=kind)
        common = {"hw_watchdog": False}
        profile = VehicleProfile(path=None, devices={"motors": {"address": f"can://virtual/fuzz-{kind}"}})
        if kind == "odrive":
            self.corpus = odrive_corpus()
            self.svc: RecordingOdrive | RecordingVesc = RecordingOdrive(
                "motors", profile=profile, config_path=workdir / "odrive.toml", transport=self.transport,
                settings=common)
            self.frame: Callable[[bytes], can.Message] = self._odrive_frame
        else:
            self.corpus = vesc_corpus()
            self.svc = RecordingVesc("motors", profile=profile, config_path=workdir / "vesc.toml",
                                     transport=self.transport, settings={**common, "odometry_source": "velocity"})
            self.frame = self._vesc_frame
        self.svc.sent = []
        self.stamp = 1000.0
        self.track = float(self.svc.config.get("track_width_m"))

    @staticmethod
    def _odrive_frame(data: bytes) -> can.Message:
        arb = struct.unpack("<H", data[:2].ljust(2, b"\0"))[0] & 0x7FF
        return can.Message(arbitration_id=arb, data=data[2:10], is_extended_id=False)

    @staticmethod
    def _vesc_frame(data: bytes) -> can.Message:
        arb = struct.unpack(">H", data[:2].ljust(2, b"\0"))[0]
        return can.Message(arbitration_id=arb, data=data[2:10], is_extended_id=True)

    def run(self, data: bytes) -> None:
        msg = self.frame(data)
        self.stamp += 0.005
        msg.timestamp = self.stamp
        try:
            self.svc._dispatch(msg)   # the run loop's frame path: ValueError is a counted drop
        except Exception as exc:  # noqa: BLE001 - nothing else may escape
            raise FuzzViolation(f"{type(exc).__name__}: {exc} escaped the {self.name} driver for {data!r}") from exc
        try:
            for sent in self.svc.sent:
                check_motion_message(sent, max_speed=20.0, track_width=self.track)
        except FuzzViolation as exc:
            raise FuzzViolation(f"{exc} after {data!r}") from None
        finally:
            self.svc.sent.clear()

    def close(self) -> None:
        self.transport.stop()


def lcm_corpus() -> list[bytes]:
    """Encoded messages of several types (strings, arrays, nested headers)."""
    state = t.StateInformation()
    state.sensor_name, state.reference_frame = "compass", "NED"
    state.set(psi=1.0, psi_sigma=0.01, x=3.0, x_sigma=0.5)
    health = t.Health()
    health.name, health.status = "gps", "ok"
    raw = t.RawSerial()
    raw.device, raw.data = "gps", b"$GPGGA,1*00\r\n"
    raw.length = len(raw.data)
    return [m.encode() for m in (state, health, t.PercentageCommand(), raw, t.Failsafe(), t.StopCommand())]


class LcmTarget(Target):
    """The receive path's decode in process: the signature check, then the type registry's decode.

    Half the inputs are signed as they are (so they reach decode), half go in as packets.
    """

    name = "lcm"

    def __init__(self, *, lcm_url: str) -> None:
        self.registry, self.malformed = REGISTRY, MalformedMessage
        self.transport = Transport(lcm_url, name="fuzz-lcm")
        auth = self.transport.auth
        assert auth is not None, "a bus key is needed (use_run_key)"
        self.auth = auth
        payloads = lcm_corpus()
        self.corpus = payloads + [auth.sign("FUZZ", p) for p in payloads]
        self.flip = False

    def run(self, data: bytes) -> None:
        self.flip = not self.flip
        try:
            packet = self.auth.sign("FUZZ", data) if self.flip else data
            verdict = self.auth.verify("FUZZ", packet)
            if verdict != OK and self.flip:
                return   # replayed/forged by the mutation of an already signed packet
            try:
                self.registry.decode(data if self.flip else packet[:-TRAILER_LEN], None)
            except self.malformed:
                pass
        except Exception as exc:  # noqa: BLE001 - nothing but MalformedMessage may come out of decode
            raise FuzzViolation(f"{type(exc).__name__}: {exc} escaped the LCM receive path for {data!r}") from exc

    def close(self) -> None:
        self.transport.stop()


def make_target(name: str, *, workdir: Path, lcm_url: str) -> Target:
    """``compass-nmea``, ``compass-os5000``, ``odrive``, ``vesc`` or ``lcm``."""
    if name.startswith("compass-"):
        return CompassTarget(name.split("-", 1)[1], workdir=workdir, lcm_url=lcm_url)
    if name == "lcm":
        return LcmTarget(lcm_url=lcm_url)
    return CanTarget(name, workdir=workdir, lcm_url=lcm_url)


TARGETS = ("compass-nmea", "compass-os5000", "odrive", "vesc", "lcm")


def run_seeded(target: Target, *, seed: int, count: int) -> int:
    """Feed *count* mutated inputs (and the corpus itself) to *target*; returns how many ran."""
    for data in target.corpus:
        target.run(data)
    mutator = Mutator(target.corpus, seed=seed, nmea=target.nmea)
    for _ in range(count):
        target.run(mutator.next())
    return count + len(target.corpus)
