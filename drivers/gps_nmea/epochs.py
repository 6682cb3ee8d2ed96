"""Grouping a GNSS receiver's sentences into epochs: one solution, one time, any number of talkers.

The rules, in order (docs/drivers-serial.md lists them beside gpsd's):

1. *Sentence times draw the boundaries.* A sentence whose UTC time differs from the
   pending epoch's ends it (GGA at 10 Hz with RMC and ZDA once a second: the RMC and ZDA
   join the GGA of their own time). Sentences without a time (GSA, VTG, HDT) join the
   pending epoch.
2. *One sentence per talker and kind.* ``$GPGGA`` then ``$GAGGA`` of the same time are one
   epoch (a multi-constellation receiver's per-system sentences); the same talker and kind
   again starts the next epoch (a receiver that stamps whole seconds at 5 Hz). GSA, GSV,
   TXT (one per constellation) and ZDA (a repeated ZDA says nothing new) never do.
3. *Silence* (the caller's :meth:`GpsEpochCollector.flush`) ends the pending epoch, and
   so does a 65th sentence (no receiver sends that many for one solution).
4. *Completion.* Once the receiver's epochs have held the same talkers and kinds for at
   least ``learn_span_s`` of wall time (two epochs at least), that content is *expected*
   and an epoch that holds all of it ends with its last sentence, without waiting for the
   silence. Epochs whose content varies within that span (a 1 Hz RMC among 10 Hz GGA)
   are never learned: they end by rules 1-3. The span is of *consecutive* epochs: every
   epoch handed out, the ones that end on completion included, continues or restarts it,
   so two bursts cut at the same point by silences seconds apart, with whole epochs
   between them, are never learned as the receiver's content.
5. *Supplements, never a second fix.* A sentence that belongs to an epoch already handed
   out -- the ended epoch's time and a talker and kind it did not hold, or no time right
   after an epoch that ended on completion -- opens a *supplement* epoch
   (``Epoch.supplement``) with that time: the caller merges it into the epoch it belongs
   to and publishes only what is new (a velocity, a date), never the position again. A
   supplement after completion also switches completion off (``varying``) until
   :meth:`reset`, so the receiver's later epochs come whole. An HDT (no time) that finds
   no epoch pending belongs to the preceding epoch, never to the following one; so do
   sentences without a time that never meet one (a GSA alone between two silences), and
   an epoch that began without a time and then meets the published epoch's time.
6. *A timeless no-fix sentence never opens the next epoch.* A sentence of a kind that
   carries a time, sent with its time empty (``$GPGLL,,,,,,V,N``: the receiver has no
   solution for it), that finds no epoch pending belongs to the preceding epoch when that
   epoch did not hold its talker and kind (the rest of a burst cut by a silence, like an
   HDT); else it opens an epoch of its own. Either way a sentence with a time ends that
   epoch: it is never the start of the next one, whose own sentence of that kind would
   then split it in two.
"""

from __future__ import annotations

import datetime as dt
from collections import Counter
from dataclasses import dataclass

from u2sa_hw.drivers.nmea_fields import Epoch, Sentence, utc_time

Key = tuple[str, str]   # (talker, kind)
GPS_REPEATABLE = frozenset({"GSA", "GSV", "TXT", "ZDA"})
TIMED_KINDS = frozenset({"GGA", "GNS", "RMC", "GLL", "GST", "ZDA"})   # kinds whose sentences carry a UTC time
LEARN_SPAN_S = 2.0
MAX_EPOCH_SENTENCES = 64   # more in one epoch is no receiver's output (a flood of one repeatable kind): end it


@dataclass
class _Ended:
    """What is remembered of the latest epoch handed out."""

    time: dt.time | None
    keys: frozenset[Key]
    early: bool           # ended on completion, and the line has not gone quiet since


class GpsEpochCollector:
    """Groups parsed GNSS sentences into epochs (rules in the module docstring)."""

    def __init__(self, *, end_on_complete: bool = True, learn_span_s: float = LEARN_SPAN_S,
                 repeatable: frozenset[str] = GPS_REPEATABLE, timed: frozenset[str] = TIMED_KINDS) -> None:
        self.end_on_complete = end_on_complete
        self.learn_span_s = learn_span_s
        self.repeatable = repeatable
        self.timed = timed
        self._pending: Epoch | None = None
        self._void = False   # the pending epoch has no time yet and holds a timed kind sent without one (rule 6)
        self._keys: Counter[Key] = Counter()
        self._ended: _Ended | None = None
        self._run: tuple[Counter[Key], float] | None = None   # the content of the latest epochs, alike since
        self.expected: Counter[Key] | None = None
        self.completed = 0   # epochs ended on completion
        self.late = 0        # sentences that came after their epoch had been handed out (merged as supplements)
        self.varying = False

    @property
    def pending(self) -> Epoch | None:
        """The epoch being collected, if any."""
        return self._pending

    @property
    def mode(self) -> str:
        """How epochs end now: ``"on completion"``, ``"learning"`` or ``"on time or silence"``."""
        if not self.end_on_complete or self.varying:
            return "on time or silence"
        return "on completion" if self.expected is not None else "learning"

    def add(self, sentence: Sentence, *, received: float) -> list[Epoch]:
        """Add *sentence*; returns the epochs it ended (the previous one, its own when it completes it)."""
        when = utc_time(sentence.msg)
        key = (sentence.talker, sentence.kind)
        done: list[Epoch] = []
        cur = self._pending
        if cur is not None and self._starts_new(cur, key, when):
            done.append(self._end(cur))
            cur = None
        void = when is None and key[1] in self.timed
        if cur is None:
            cur = self._open(key, when, received, void)
        if cur.time is None and when is not None:
            cur.time = when
            cur.supplement = cur.supplement or self._belongs_to_ended(when, {*self._keys, key})
        elif void:
            self._void = cur.time is None
        cur.sentences.append(sentence)
        self._keys[key] += 1
        if not cur.supplement and self._complete():
            self._ended = _Ended(cur.time, frozenset(self._keys), True)
            self._pending, self._keys = None, Counter()
            self.completed += 1
            expected, run = self.expected, self._run
            if run is None or run[0] is not expected:
                # a whole epoch after another content (a burst cut by a silence): the span of alike
                # epochs starts again here, so a cut seconds ago is never learned as complete (rule 4)
                self._run = (expected, cur.received)  # type: ignore[assignment]
            done.append(cur)
        return done

    def _starts_new(self, cur: Epoch, key: Key, when: dt.time | None) -> bool:
        if when is not None and cur.time is not None and when != cur.time:
            return True
        if when is not None and cur.time is None and self._void:
            return True   # a timeless no-fix sentence (rule 6) never opens the epoch of the next time
        if len(cur.sentences) >= MAX_EPOCH_SENTENCES:
            return True
        if key[1] in self.repeatable:
            return False
        # a supplement also ends on a repeat of what its epoch already held (the next epoch's VTG)
        ended = self._ended
        return key in self._keys or (cur.supplement and ended is not None and key in ended.keys)

    def _open(self, key: Key, when: dt.time | None, received: float, void: bool) -> Epoch:
        ended = self._ended
        supplement = False
        self._void = void
        if ended is not None and (key not in ended.keys or key[1] in self.repeatable):
            if when is not None:
                supplement = when == ended.time
            else:
                supplement = ended.early or void or key[1] == "HDT"
        if supplement:
            self.late += 1
            if ended is not None and ended.early:
                self.varying = True
            epoch = Epoch(received=received, time=ended.time if ended else None, supplement=True)
        else:
            epoch = Epoch(received=received)
        self._pending = epoch
        return epoch

    def _belongs_to_ended(self, when: dt.time, keys: set[Key]) -> bool:
        """True when an epoch that began without a time turns out to carry the ended epoch's time and
        repeats nothing of it (a GSA after a silence, then the RMC of the epoch already handed out)."""
        ended = self._ended
        if ended is None or when != ended.time:
            return False
        if any(k in ended.keys and k[1] not in self.repeatable for k in keys):
            return False
        self.late += 1
        return True

    def _complete(self) -> bool:
        expected = self.expected
        if expected is None or self.varying or not self.end_on_complete:
            return False
        have = self._keys
        return all(have[k] >= n for k, n in expected.items())

    def _end(self, epoch: Epoch) -> Epoch:
        """End *epoch* (the pending one) the ordinary way, learning its content."""
        keys, before = self._keys, self._ended
        self._pending, self._keys = None, Counter()
        if epoch.supplement:
            self.late += len(epoch.sentences) - 1
            held = before.keys if before is not None and before.time == epoch.time else frozenset()
            self._ended = _Ended(epoch.time, held | frozenset(keys), False)
            return epoch
        if epoch.time is None and before is not None and before.time is not None and not any(
                k in before.keys and k[1] not in self.repeatable for k in keys):
            # sentences without a time that never met one (a GSA alone between two silences) belong
            # to the preceding epoch
            epoch.supplement, epoch.time = True, before.time
            self.late += len(epoch.sentences)
            self._ended = _Ended(before.time, before.keys | frozenset(keys), False)
            return epoch
        self._ended = _Ended(epoch.time, frozenset(keys), False)
        if self.end_on_complete and not self.varying:
            self._learn(keys, epoch.received)
        return epoch

    def _learn(self, keys: Counter[Key], received: float) -> None:
        run = self._run
        if run is None or run[0] != keys:
            self._run = (keys, received)   # a new content: the span starts again
        elif received - run[1] >= self.learn_span_s:
            self.expected = run[0]

    def dropped(self, kind: str, talker: str = "") -> Epoch | None:
        """A *kind* sentence from *talker* was dropped (bad checksum). If it would have started a
        new epoch (one the pending epoch already holds), the pending epoch is over: end and return it,
        so a run of corrupted sentences does not hold the last good epoch back."""
        cur = self._pending
        if cur is None or kind in self.repeatable:
            return None
        held = (talker, kind) in self._keys if talker else any(k == kind for _, k in self._keys)
        return self._end(cur) if held else None

    def flush(self) -> Epoch | None:
        """End the pending epoch (the line went quiet); returns it, or None when there is none."""
        if self._ended is not None:
            self._ended.early = False
        cur = self._pending
        return None if cur is None else self._end(cur)

    def reset(self) -> None:
        """Drop the pending epoch and everything learned (the port was lost or reopened)."""
        self._pending, self._keys, self._ended, self._run = None, Counter(), None, None
        self._void = False
        self.expected = None
        self.varying = False
