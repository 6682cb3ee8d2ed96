"""NMEA 0183 lines to parsed sentences, typed field access, and grouping sentences into epochs.

Shared by the GPS and compass drivers. Parsing is pynmeagps's (``NMEAReader.parse`` with
checksum validation); this module decides what a line *is* before and after that:

- bytes before the last ``$`` are line noise (a garbage burst glued to the next sentence)
  and are dropped; the sentence after them is still used;
- a sentence without ``*HH`` or with non-ASCII bytes is :class:`MalformedSentence`;
- a wrong checksum is :class:`BadChecksum` (it names the sentence kind, e.g. ``GGA``);
- a sentence pynmeagps does not know (or a proprietary ``$P...`` one) parses to ``None``,
  and so do a blank line and an encapsulated sentence (``!AIVDM`` AIS data sharing the
  line): they are not errors, just not for these drivers.

pynmeagps turns an unparseable field into ``""`` and leaves fields missing from a short
sentence unset, so fields are read with :func:`number` / :func:`text`, which give ``None``
/ ``""`` for both and never a stale or zero value; :func:`number` also gives None for a
value that is no finite float (a 400-digit field, ``inf``), so no caller meets an overflow.

An *epoch* is the burst of sentences a receiver sends for one solution (:class:`Epoch`);
the GPS driver's rules for where one ends are in :mod:`u2sa_hw.drivers.gps_nmea.epochs`.
"""

from __future__ import annotations

import datetime as dt
import math
import re
from dataclasses import dataclass, field
from typing import Any

from pynmeagps import VALMSGID, NMEAMessage, NMEAReader
from pynmeagps.exceptions import NMEAMessageError, NMEAParseError, NMEATypeError
from pynmeagps.nmeahelpers import calc_checksum
from pynmeagps.nmeatypes_get import NMEA_PAYLOADS_GET

_CHECKSUM = re.compile(r"\*([0-9A-Fa-f]{2})\s*$")
# kinds that may appear several times in one epoch (one GSA per constellation, one XDR per transducer)
REPEATABLE_KINDS = frozenset({"GSA", "GSV", "XDR", "TXT"})


class SentenceError(ValueError):
    """A line that is not a usable sentence; ``kind`` is its sentence id (``GGA``) or ``"?"``."""

    def __init__(self, message: str, *, kind: str = "?", talker: str = "") -> None:
        super().__init__(message)
        self.kind = kind
        self.talker = talker


class BadChecksum(SentenceError):
    """The sentence's checksum does not match its content."""


class MalformedSentence(SentenceError):
    """No ``$``, no ``*HH`` checksum, non-ASCII bytes, or fields pynmeagps cannot take."""


@dataclass(frozen=True)
class Sentence:
    """One parsed sentence: its talker (``GP``), kind (``GGA``) and the pynmeagps message."""

    talker: str
    kind: str
    msg: NMEAMessage
    noise_bytes: int = 0  # bytes of line noise dropped before the ``$``
    fields: tuple[str, ...] = ()  # the raw field texts after the address (``fields[1]`` is GGA's latitude)


def sentence_text(line: bytes) -> tuple[str, int]:
    """The sentence in *line* from its last ``$`` (CR LF stripped) and how many noise bytes preceded it."""
    start = line.rfind(b"$")
    if start < 0:
        raise MalformedSentence(f"no '$' in {line[:40]!r}")
    body = line[start:].rstrip(b"\r\n")
    try:
        return body.decode("ascii"), start
    except UnicodeDecodeError:
        raise MalformedSentence(f"non-ASCII bytes in {body[:40]!r}") from None


def address_of(text: str) -> tuple[str, str]:
    """``(talker, kind)`` of ``$GPGGA,...``; proprietary ``$PXXX`` gives ``("P", "XXX")``.

    An address that is no talker and kind (garbage, ``$095625``) gives kind ``"?"``, so
    counters keyed by kind stay a handful of names whatever the line noise."""
    address = text[1:].split(",", 1)[0].split("*", 1)[0]
    if address.startswith("P"):
        talker, kind = "P", address[1:]
    else:
        talker, kind = address[:2], address[2:]
    if not (1 <= len(kind) <= 8 and kind.isascii() and kind.isalnum() and kind.isupper()):
        return talker, "?"
    return talker, kind


def checked_body(text: str, address: tuple[str, str] | None = None) -> str:
    """The content between ``$`` and ``*`` after checking the checksum; raises BadChecksum/MalformedSentence.

    *address* is :func:`address_of` *text* when the caller has it already."""
    talker, kind = address if address is not None else address_of(text)
    match = _CHECKSUM.search(text)
    if match is None:
        raise MalformedSentence(f"no *HH checksum in {text[:40]!r}", kind=kind or "?", talker=talker)
    body = text[1:match.start()]
    expected = calc_checksum(body)
    if match.group(1).upper() != expected:
        raise BadChecksum(f"checksum {match.group(1)} should be {expected} in {text[:60]!r}", kind=kind or "?",
                          talker=talker)
    return body


def is_foreign(line: bytes) -> bool:
    """True for a line that is no error but not for an NMEA sentence driver: blank, or an
    encapsulated sentence (``!AIVDM``/``!AIVDO`` AIS) sharing the port."""
    stripped = line.strip()
    return not stripped or (stripped[:1] == b"!" and b"$" not in stripped)


def parse_sentence(line: bytes) -> Sentence | None:
    """Parse one line with pynmeagps; None for a well-formed sentence it does not know.

    Raises BadChecksum or MalformedSentence; never anything else for any input bytes.
    A blank line and an encapsulated ``!`` sentence (AIS) give None (:func:`is_foreign`).
    """
    if is_foreign(line):
        return None
    text, noise = sentence_text(line)
    talker, kind = address_of(text)
    body = checked_body(text, (talker, kind))
    if talker == "P" or len(talker) != 2 or kind not in NMEA_PAYLOADS_GET:
        return None  # proprietary, or a sentence pynmeagps has no field table for
    try:
        # the checksum is checked above (and names the sentence kind); pynmeagps need not do it again
        msg = NMEAReader.parse(text.encode("ascii"), validate=VALMSGID)
    except (NMEAParseError, NMEAMessageError, NMEATypeError, ValueError, IndexError, TypeError) as exc:
        raise MalformedSentence(f"{talker}{kind}: {exc}", kind=kind) from None
    if msg is None:
        return None
    return Sentence(talker=talker, kind=kind, msg=msg, noise_bytes=noise, fields=tuple(body.split(",")[1:]))


def number(msg: Any, name: str) -> float | None:
    """Field *name* as a finite float, or None when empty, unparseable or absent."""
    value = getattr(msg, name, None)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        value = float(value)
    except OverflowError:   # pynmeagps makes an int of a digit string of any length
        return None
    return value if math.isfinite(value) else None


def text(msg: Any, name: str) -> str:
    """Field *name* as a stripped string (``""`` when empty or absent)."""
    value = getattr(msg, name, None)
    return value.strip() if isinstance(value, str) else ""


def utc_time(msg: Any) -> dt.time | None:
    """The sentence's UTC time of day (``time`` field), or None."""
    value = getattr(msg, "time", None)
    return value if isinstance(value, dt.time) else None


def signed(value: float | None, hemisphere: str, *, negative: str = "W") -> float | None:
    """*value* with the sign its hemisphere letter gives (``W``/``S`` negative); None stays None."""
    if value is None:
        return None
    return -value if hemisphere.upper() == negative else value


@dataclass
class Epoch:
    """The sentences of one solution, in arrival order; ``received`` is the wall time (s) of the first."""

    received: float
    time: dt.time | None = None
    sentences: list[Sentence] = field(default_factory=list)
    supplement: bool = False   # sentences that came after their epoch (same time) was handed out

    def kinds(self) -> list[str]:
        """The sentence kinds, in arrival order (repeats kept)."""
        return [s.kind for s in self.sentences]

    def first(self, kind: str) -> NMEAMessage | None:
        """The first sentence of *kind* in this epoch, or None."""
        return next((s.msg for s in self.sentences if s.kind == kind), None)

    def all(self, kind: str) -> list[NMEAMessage]:
        """Every sentence of *kind* in this epoch."""
        return [s.msg for s in self.sentences if s.kind == kind]

    def talkers(self) -> set[str]:
        """The talker ids seen in this epoch."""
        return {s.talker for s in self.sentences}

