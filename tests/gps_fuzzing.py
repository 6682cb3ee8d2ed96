"""Seeded mutation fuzzing of the GPS driver: valid sentences, mutated so most still pass the checksum.

Used by tests/test_gps_fuzz.py (a bounded run in ``make test``) and bench/fuzz_gps.py (long
runs, atheris where it installs). Seeds are valid sentences of every kind the driver reads,
composed by gps_stream_builder with random solutions; :func:`mutate` applies one to three of:
bit flip, digit inflation (a field becomes hundreds of digits, ``1e308``, ``inf``, ``nan``),
field deletion, duplication, swap or emptying, truncation, and a duplicated or dropped
sentence; then recomputes the checksum (nine times in ten) so the sentence reaches the
field parsing instead of stopping at the checksum. :func:`check_message` asserts what every
published State Information must satisfy.
"""

from __future__ import annotations

import datetime as dt
import math
import random
from typing import Callable

from gps_stream_builder import BUILDERS, START, Solution, checksum

from u2sa_hw.drivers.gps_nmea import limits as lim
from u2sa_hw import lcmtypes as t

INFLATIONS = ("9" * 20, "1" * 400, "1e308", "-1e308", "inf", "nan", "-0", "1e-320", "99999999999.999999",
              "0x1F", "+5", "1_000", "٣")   # the last is an Arabic-Indic digit: non-ASCII


def random_solution(rng: random.Random) -> Solution:
    """A solution anywhere on earth, moving or not, at a random time."""
    return Solution(
        when=START + dt.timedelta(seconds=rng.uniform(0, 86400 * 3)),
        lat=rng.uniform(-89.9, 89.9), lon=rng.uniform(-179.9, 179.9), alt=rng.uniform(-400, 9000),
        sep=rng.uniform(-100, 80), speed=rng.choice((0.0, rng.uniform(0, 100))),
        course=rng.choice((None, rng.uniform(0, 359.99))), heading=rng.uniform(0, 359.99),
        sats=rng.randint(0, 40), hdop=rng.uniform(0.5, 20), vdop=rng.uniform(0.5, 30), quality=rng.randint(0, 8))


def seed_line(rng: random.Random) -> bytes:
    """One valid sentence of a random kind and talker."""
    kind = rng.choice(sorted(BUILDERS))
    talker = rng.choice(("GP", "GN", "GL", "GA", "GB", "GQ"))
    return BUILDERS[kind](random_solution(rng), talker=talker)


def _body(line: bytes) -> bytes:
    text = line.strip()
    return text[1:text.index(b"*")]


def mutate(rng: random.Random, line: bytes) -> bytes:
    """*line* with one to three mutations; the checksum recomputed nine times in ten."""
    original = _body(line)
    fields = original.split(b",")
    for _ in range(rng.randint(1, 3)):
        op = rng.randrange(8)
        i = rng.randrange(1, len(fields)) if len(fields) > 1 else 0
        if op == 0:                                   # bit flip
            raw = bytearray(b",".join(fields) or b"$")
            pos = rng.randrange(len(raw))
            raw[pos] ^= 1 << rng.randrange(8)
            fields = bytes(raw).split(b",")
        elif op in (1, 2):                            # digit inflation
            fields[i] = rng.choice(INFLATIONS).encode() if op == 1 else fields[i] + b"9" * rng.randint(10, 400)
        elif op == 3 and len(fields) > 1:             # field deletion
            del fields[i]
        elif op == 4:                                 # field duplication
            fields.insert(i, fields[i])
        elif op == 5 and len(fields) > 2:             # swap two fields
            j = rng.randrange(1, len(fields))
            fields[i], fields[j] = fields[j], fields[i]
        elif op == 6:                                 # empty a field
            fields[i] = b""
        else:                                         # truncation
            joined = b",".join(fields)
            fields = joined[:rng.randrange(len(joined) + 1)].split(b",")
    data = b",".join(fields)
    if rng.random() < 0.9:
        value = 0
        for byte in data:
            value ^= byte
        suffix = f"*{value:02X}".encode()
    else:
        suffix = b"*" + checksum(original.decode("ascii")).encode()
    out = b"$" + data + suffix + b"\r\n"
    if rng.random() < 0.05:
        out = out[:rng.randrange(1, len(out))]           # a line cut short (no CR LF)
    return out


def check_message(msg: t.StateInformation) -> None:
    """What every published GPS message must satisfy (GEODETIC frame): finite, in range."""
    for name in msg.present_fields():
        value = msg.get(name)
        assert math.isfinite(value), f"{name} = {value!r}"
        if name.endswith("_sigma"):
            assert 0 < value <= 1e5, f"{name} = {value!r}"
    if msg.has("x"):
        assert msg.reference_frame == "GEODETIC"
        assert lim.within(msg.x, lim.LAT_DEG) and lim.within(msg.y, lim.LON_DEG), (msg.x, msg.y)
    if msg.has("z"):
        assert lim.ALT_M.low + lim.GEOID_SEP_M.low <= msg.z <= lim.ALT_M.high + lim.GEOID_SEP_M.high, msg.z
    if msg.has("x_dot"):
        assert math.hypot(msg.x_dot, msg.y_dot) <= lim.SPEED_MPS.high + 1e-9
    if msg.has("psi"):
        assert -math.pi <= msg.psi < math.pi


def fuzz_cases(rng: random.Random, count: int) -> list[bytes]:
    """*count* lines: mostly mutated sentences, some valid ones between them (so epochs form)."""
    out = []
    for _ in range(count):
        line = seed_line(rng)
        out.append(line if rng.random() < 0.3 else mutate(rng, line))
    return out


def feed(handle_line: Callable[[bytes, float], None], handle_idle: Callable[[], None], rng: random.Random,
         lines: list[bytes]) -> None:
    """Feed *lines* as a read loop would, with a silence after one line in eight."""
    for k, line in enumerate(lines):
        handle_line(line, 1000.0 + k * 0.01)
        if rng.random() < 0.125:
            handle_idle()
    handle_idle()
