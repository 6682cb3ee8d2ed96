"""Grouping a compass's sentences into bursts, and a burst into one reading.

A compass sends its readings in bursts -- e.g. ``XDR`` pitch, ``XDR`` roll, ``HDM`` -- that
carry no time, often back to back with no silence between them. A burst must hold the
sentences of *one* measurement: the heading published with its own burst's pitch and roll,
never with the next one's. :class:`BurstGrouper` ends a burst (rules in order):

1. *Silence*: a line whose idle time -- the time since the previous line less its own
   transmission time (characters x ``char_time_s``) -- is ``gap_s`` or more (or that comes
   after the driver saw the line go quiet) starts a new burst; the sentence that starts a
   burst after a silence, twice in a row, is learned as the device's *first sentence*.
2. *Repeat*: a sentence whose signature (its kind; for XDR its transducer names) is already
   in the burst starts a new one -- a burst never holds two readings of one quantity.
3. *First sentence*: once learned (by rule 1, or by timing: the signature that follows the
   longest idle time by a margin well above the jitter, over at least 8 bursts), its
   arrival starts a new burst.
4. *Complete*: once two bursts in a row held the same signatures, a burst that holds them
   all ends at once, without waiting for the next sentence or the silence.
5. With no first sentence known yet, a heading sentence ends its burst (the common
   order: attitude transducers, then the heading).

Fail safe while learning: until the first sentence is known, the order of the device's
sentences is a guess (``HDM, XDR, XDR`` evenly spaced looks the same as ``XDR, XDR, HDM``),
so a burst that began then is published one sentence at a time (:meth:`Burst.pieces`):
a heading, a pitch or a roll is never combined with another burst's values. A device that
spaces its sentences evenly, with neither silence nor a longer pause between bursts,
keeps publishing one message per sentence.

A stream that only sends XDR pitch/roll (no heading) thus gives one reading per XDR
(rule 2), not one message per silence.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from u2sa_hw.drivers.compass.sentences import CompassPart

MIN_TIMING_SAMPLES = 8
_EMA = 0.2
HEADING_PREFERENCE = ("THS", "HDT", "PASHR", "PTNTHTM", "PTNTHPR", "HDG", "HDM")


@dataclass
class Burst:
    """The parts of one burst in arrival order; ``received`` is the wall time (s) of its first line,
    ``arrivals`` that of each part; ``ordered``: the device's first sentence was known when it began."""

    received: float
    parts: list[CompassPart] = field(default_factory=list)
    arrivals: list[float] = field(default_factory=list)
    ordered: bool = False

    def signatures(self) -> frozenset[str]:
        """The signatures the burst holds."""
        return frozenset(p.signature for p in self.parts)

    def pieces(self) -> list[Burst]:
        """The burst as it is published: whole when ordered (or of one sentence); otherwise one piece per
        sentence, each stamped with its own arrival -- its sentences may belong to two of the device's bursts."""
        if self.ordered or len(self.parts) <= 1:
            return [self]
        return [Burst(received=at, parts=[part], arrivals=[at]) for part, at in zip(self.parts, self.arrivals)]


@dataclass
class _Timing:
    mean: float = 0.0
    jitter: float = 0.0
    samples: int = 0

    def add(self, idle: float) -> None:
        if self.samples == 0:
            self.mean = idle
        else:
            self.jitter += _EMA * (abs(idle - self.mean) - self.jitter)
            self.mean += _EMA * (idle - self.mean)
        self.samples += 1


class BurstGrouper:
    """Groups :class:`CompassPart` values into bursts (rules in the module docstring)."""

    def __init__(self, *, gap_s: float, char_time_s: float = 0.0) -> None:
        self.gap_s = gap_s
        self.char_time_s = char_time_s      # how long one character takes on the wire (frame bits / baud)
        self.first: str | None = None       # the learned first signature of a burst
        self.first_from = ""                # "silence" or "timing"
        self.complete: frozenset[str] | None = None
        self._pending: Burst | None = None
        self._last_received: float | None = None
        self._after_silence = True
        self._silence_starts: list[str] = []
        self._previous: frozenset[str] | None = None
        self._timing: dict[str, _Timing] = {}

    def add(self, part: CompassPart, *, received: float, chars: int = 0) -> list[Burst]:
        """Add one part read at *received* (a line of *chars* characters); returns the bursts it ended."""
        done: list[Burst] = []
        # idle: how long the line was quiet before this line's first character (it arrived with its last)
        idle = None if self._last_received is None else received - self._last_received - chars * self.char_time_s
        self._last_received = received
        silence = self._after_silence or idle is None or idle >= self.gap_s
        self._after_silence = False
        cur = self._pending
        if silence:
            self._learn_from_silence(part.signature)
        elif idle is not None:
            self._learn_from_timing(part.signature, idle)
        if cur is not None and (silence or part.signature in cur.signatures()
                                or (part.signature == self.first and cur.parts)):
            done.append(self._end())
            cur = None
        if cur is None:
            cur = self._pending = Burst(received=received, ordered=self.first is not None)
        cur.parts.append(part)
        cur.arrivals.append(received)
        held = cur.signatures()
        if self.complete is not None and held >= self.complete:
            done.append(self._end())
        elif self.first is None and part.heading is not None:
            done.append(self._end())
        return done

    def _learn_from_silence(self, signature: str) -> None:
        self._silence_starts = (self._silence_starts + [signature])[-2:]
        if len(self._silence_starts) == 2 and self._silence_starts[0] == signature:
            self.first, self.first_from = signature, "silence"

    def _learn_from_timing(self, signature: str, idle: float) -> None:
        self._timing.setdefault(signature, _Timing()).add(idle)
        if self.first_from == "silence" or self.complete is None or len(self.complete) < 2:
            return
        stats = [self._timing.get(s) for s in self.complete]
        if any(s is None or s.samples < MIN_TIMING_SAMPLES for s in stats):
            return
        ranked = sorted(((self._timing[s].mean, s) for s in self.complete), reverse=True)
        (best, name), (second, _) = ranked[0], ranked[1]
        margin = 3.0 * max(t.jitter for t in stats if t is not None) + 0.001
        if best - second > margin:
            self.first, self.first_from = name, "timing"

    def _end(self) -> Burst:
        burst = self._pending
        assert burst is not None
        self._pending = None
        held = burst.signatures()
        if self._previous == held and len(burst.parts) == len(held):
            self.complete = held
        self._previous = held
        return burst

    def dropped(self, kind: str) -> Burst | None:
        """A *kind* sentence was dropped (bad checksum). When the pending burst already holds one (not
        XDR, whose transducers may differ), it was the next burst's: end the pending one now."""
        cur = self._pending
        if cur is None or kind == "XDR" or all(p.kind != kind for p in cur.parts):
            return None
        return self._end()

    def flush(self) -> Burst | None:
        """The line went quiet: end the pending burst (None when there is none)."""
        self._after_silence = True
        return self._end() if self._pending is not None else None

    def reset(self) -> None:
        """Forget the pending burst and everything learned (the port was lost or reopened)."""
        self.__init__(gap_s=self.gap_s, char_time_s=self.char_time_s)  # type: ignore[misc]

    @property
    def rule(self) -> str:
        """How bursts end now, for health: ``complete, first X (silence|timing)``, ``first X (...)``, or
        ``learning`` / ``complete, learning`` while the first sentence is not known (one message per sentence)."""
        if self.first is None:
            return "complete, learning" if self.complete is not None else "learning"
        if self.complete is not None:
            return f"complete, first {self.first} ({self.first_from})"
        return f"first {self.first} ({self.first_from})"


@dataclass(frozen=True)
class CompassReading:
    """One burst's measurement in degrees (None when not reported); sigmas when the device gave them."""

    source: str                       # the heading's sentence ("HDT", "THS", "$C", ...) or "" (no heading)
    true_heading: float | None = None
    magnetic_heading: float | None = None
    pitch: float | None = None
    roll: float | None = None
    temperature: float | None = None
    rate_deg_s: float | None = None   # rate of turn, positive turning right (clockwise from above)
    heading_sigma: float | None = None
    pitch_sigma: float | None = None
    roll_sigma: float | None = None
    mode: str = ""


def reading_from_parts(parts: list[CompassPart], *, declination_deg: float, use_hdg_variation: bool) -> CompassReading:
    """The heading (by ``HEADING_PREFERENCE``), pitch, roll and rate of turn of one burst.

    true = magnetic + declination; HDG: magnetic = sensor + deviation, and its own variation
    replaces ``declination_deg`` with *use_hdg_variation*; PTNT headings are the compass's
    own corrected value, plus ``declination_deg`` (0 when the compass applies it).
    """
    pitch = next((p.pitch for p in parts if p.pitch is not None), None)
    roll = next((p.roll for p in parts if p.roll is not None), None)
    rate = next((p.rate_deg_min / 60.0 for p in parts if p.rate_deg_min is not None), None)
    pitch_sigma = next((p.pitch_sigma for p in parts if p.pitch is not None), None)
    roll_sigma = next((p.roll_sigma for p in parts if p.roll is not None), None)
    common = dict(pitch=pitch, roll=roll, rate_deg_s=rate, pitch_sigma=pitch_sigma, roll_sigma=roll_sigma)
    for kind in HEADING_PREFERENCE:
        part = next((p for p in parts if p.kind == kind and p.heading is not None), None)
        if part is None or part.heading is None:
            continue
        if part.reference == "true":
            return CompassReading(kind, true_heading=part.heading, heading_sigma=part.heading_sigma,
                                  mode=part.mode, **common)  # type: ignore[arg-type]
        magnetic, declination = part.heading, declination_deg
        if part.reference == "sensor":
            magnetic += part.deviation or 0.0
            if use_hdg_variation and part.variation is not None:
                declination = part.variation
        true = magnetic + declination
        if not math.isfinite(true):
            continue
        return CompassReading(kind, true_heading=true, magnetic_heading=magnetic, **common)  # type: ignore[arg-type]
    return CompassReading("", **common)  # type: ignore[arg-type]
