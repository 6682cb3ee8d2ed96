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

An *epoch* is the burst of sentences a receiver sends for one solution.
:class:`EpochCollector` ends an epoch when a sentence carries a different UTC time than
the epoch so far, when a once-per-epoch sentence kind repeats, or when the caller reports
that the line went quiet (:meth:`EpochCollector.flush`). With ``end_on_complete`` it also
learns what a complete epoch holds and ends one as soon as its last sentence arrives,
instead of waiting for the silence (see :class:`EpochCollector`).
"""

from __future__ import annotations

import datetime as dt
import math
import re
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Iterable

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


class EpochCollector:
    """Groups parsed sentences into epochs (the rules are in the module docstring).

    With ``end_on_complete`` the collector learns the epoch's content: the sentence kinds,
    with their counts, of an epoch that ended the ordinary way (new UTC time, repeated kind,
    silence). Once two such epochs in a row hold the same kinds, that set is *expected*, and
    an epoch that holds all of it ends at once -- the receiver has said everything, so the
    silence after the burst is not waited for. The ordinary rules stay in force for epochs
    that never complete (a dropped sentence, a stall mid-burst).

    A receiver whose epochs differ (a ZDA once a second, a GSV cycle) can send a sentence
    after an epoch that looked complete. Until the line goes quiet, a sentence that is not
    the expected first kind and carries the ended epoch's UTC time (or no time) belongs to
    the epoch already handed out: it is *late*, dropped and counted (``late``), and ending on
    completion is switched off (``varying``) until :meth:`reset`, so such a receiver is read
    the ordinary way and loses nothing more.
    """

    def __init__(self, *, repeatable: Iterable[str] = REPEATABLE_KINDS, end_on_complete: bool = False) -> None:
        self.repeatable = frozenset(repeatable)
        self.end_on_complete = end_on_complete
        self._pending: Epoch | None = None
        self._pending_kinds: Counter[str] = Counter()
        self.expected: Counter[str] | None = None   # the content of a complete epoch, once learned
        self.first_kind = ""                        # the expected epoch's first sentence kind
        self._last_kinds: tuple[Counter[str], str] | None = None   # the previous ordinarily ended epoch
        self._ended_early: Epoch | None = None      # ended on completion; the line has not gone quiet since
        self.completed = 0   # epochs ended on completion
        self.late = 0        # sentences that came after their epoch had ended on completion
        self.varying = False

    @property
    def pending(self) -> Epoch | None:
        """The epoch being collected, if any."""
        return self._pending

    @property
    def mode(self) -> str:
        """How epochs end now: ``"on completion"``, ``"learning"`` or ``"on silence"``."""
        if not self.end_on_complete or self.varying:
            return "on silence"
        return "on completion" if self.expected is not None else "learning"

    def add(self, sentence: Sentence, *, received: float) -> Epoch | None:
        """Add *sentence*; returns the epoch it ended: the previous one, or its own when it completes it."""
        when = utc_time(sentence.msg)
        if self._ended_early is not None:
            if self._is_late(sentence.kind, when):
                self.late += 1
                self.varying = True
                return None
            self._ended_early = None
        done = None
        cur = self._pending
        if cur is not None and self._starts_new(cur, sentence.kind, when):
            done, cur = self._end(), None
        if cur is None:
            cur = self._pending = Epoch(received=received)
        if cur.time is None and when is not None:
            cur.time = when
        cur.sentences.append(sentence)
        self._pending_kinds[sentence.kind] += 1
        # the sentence that ended the previous epoch does not also end its own (only a one-sentence epoch could)
        if done is None and self._complete():
            self._ended_early = cur
            self.completed += 1
            self._pending, self._pending_kinds = None, Counter()
            return cur
        return done

    def _starts_new(self, cur: Epoch, kind: str, when: dt.time | None) -> bool:
        if when is not None and cur.time is not None and when != cur.time:
            return True
        return kind not in self.repeatable and kind in self._pending_kinds

    def _complete(self) -> bool:
        expected = self.expected
        if expected is None or self.varying or not self.end_on_complete:
            return False
        have = self._pending_kinds
        return all(have[kind] >= n for kind, n in expected.items())

    def _is_late(self, kind: str, when: dt.time | None) -> bool:
        if kind == self.first_kind:
            return False
        ended = self._ended_early
        return when is None or ended is None or ended.time is None or when == ended.time

    def _end(self) -> Epoch | None:
        """End the pending epoch the ordinary way, learning its content."""
        done, kinds = self._pending, self._pending_kinds
        self._pending, self._pending_kinds = None, Counter()
        if done is not None and self.end_on_complete and not self.varying:
            first = done.sentences[0].kind
            if self._last_kinds == (kinds, first):
                self.expected, self.first_kind = kinds, first
            self._last_kinds = (kinds, first)
        return done

    def dropped(self, kind: str) -> Epoch | None:
        """A *kind* sentence was dropped (bad checksum). If it would have started a new epoch
        (a kind the pending epoch already holds), the pending epoch is over: end and return it,
        so a run of corrupted sentences does not hold the last good epoch back."""
        cur = self._pending
        if cur is None or kind in self.repeatable or kind not in self._pending_kinds:
            return None
        self._ended_early = None
        return self._end()

    def flush(self) -> Epoch | None:
        """End the pending epoch (the line went quiet); returns it, or None when there is none."""
        self._ended_early = None
        return self._end()

    def reset(self) -> None:
        """Drop the pending epoch and everything learned (the port was lost or reopened)."""
        self._pending, self._pending_kinds = None, Counter()
        self.expected, self.first_kind, self._last_kinds, self._ended_early = None, "", None, None
        self.varying = False
