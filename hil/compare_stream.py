"""One stream of ``u2sa replay --compare`` compared message by message: :func:`compare_stream`.

The two sides are paired in order and by content (:func:`align`, hil/stream_align.py); the rules
for what is a difference and what a note -- the edges where the recording cuts the input, a
partial message at a cut, the fields the rest of the system decides, the windows where the
recording machine held a service up, the replayed start-up writes -- are in hil/compare.py's
docstring. The result is a :class:`StreamReport`.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass, field
from typing import Any, Sequence

from u2sa_hw.hil.compare_values import (KEPT_BY_VERDICT, SYSTEM_FIELDS, Sample, ToleranceLike, Tolerances,
                                        as_tolerances, differing_fields, values_equal)
from u2sa_hw.hil.compare_cuts import (START_CUT_NS, TAIL_CUT_NS, after_cut, cut_note, mux_decided_before, partial,
                                      recorded_times, rest_of_cut)
from u2sa_hw.hil.held_up import STOP_WINDOW_END, HeldWindow
from u2sa_hw.hil.stream_align import Pair, align_streams, content_key

@dataclass
class FieldDiff:
    """One field that differs in some messages of a stream."""

    name: str
    count: int = 0
    max_abs: float = 0.0
    first: tuple[int, Any, Any] | None = None   # (recorded index, recorded, replayed)
    first_t_ns: int | None = None               # log time of that recorded message


@dataclass
class Event:
    """A message only on one side: ``deleted`` (recorded, not replayed) or ``inserted`` (replayed only)."""

    kind: str
    index: int          # in its own stream
    t_ns: int           # log time: the recorded message's, or for an insertion the recorded one before it


@dataclass
class StreamReport:
    """The comparison of one stream."""

    key: str
    recorded: int
    replayed: int
    matched: int = 0
    differing: int = 0
    inserted: int = 0
    deleted: int = 0
    events: list[Event] = field(default_factory=list)
    fields: dict[str, FieldDiff] = field(default_factory=dict)
    time_p50_s: float | None = None
    time_max_s: float | None = None
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when nothing differs beyond the tolerances."""
        return not self.problems


def content_keys(samples: list[Sample], tol: Tolerances, skip: tuple[str, ...] = ()) -> list[Any]:
    """Each message's alignment key (hil/stream_align.py), leaving out the fields in *skip*."""
    def own(fields: dict[str, Any]) -> dict[str, Any]:
        return {n: v for n, v in fields.items() if n not in skip} if skip else fields

    return [content_key(s.type_name, own(s.fields), tol.of) for s in samples]


def align(rec: list[Sample], rep: list[Sample], *, tolerance: ToleranceLike,
          skip: tuple[str, ...] = (), keys: tuple[list[Any], list[Any]] | None = None) -> list[Pair]:
    """Pair the two streams' messages in order (hil/stream_align.py): match, differ, deleted, inserted.

    Fields in *skip* (the stream's ``SYSTEM_FIELDS``) do not steer the pairing: a difference there is a note.
    *keys*: the two sides' :func:`content_keys`, when the caller has them.
    """
    tol = as_tolerances(tolerance)
    rec_keys, rep_keys = keys or (content_keys(rec, tol, skip), content_keys(rep, tol, skip))

    def pair_cost(i: int, j: int) -> float:
        a, b = rec[i], rep[j]
        if a.type_name != b.type_name:
            return 1.0
        names = (set(a.fields) | set(b.fields)) - set(skip)
        return len([n for n in differing_fields(a, b, tol) if n not in skip]) / max(1, len(names))

    return align_streams(rec_keys, rep_keys, pair_cost=pair_cost)


def compare_stream(key: str, rec: list[Sample], rep: list[Sample], *, tolerance: ToleranceLike, edge: int,
                   rate: float | None, time_tolerance_s: float, replay_start_ns: int | None = None,
                   origin_ns: int | None = None, held: Sequence[HeldWindow] = (),
                   started_before: bool = False, recording_end_ns: int | None = None,
                   decided_before: bool = False, flowing: bool = False) -> StreamReport:
    """Compare one stream (see the module docstring); *replay_start_ns*: when the playback began; *origin_ns*:
    the log time notes count seconds from (default the stream's first recorded message); *held*: where the
    recording machine held the stream's service up (hil/held_up.py): what differs there is a note;
    *started_before*: the recording began after the stream's driver started (:func:`begun_after_start`),
    so the replayed start-up writes before the first recorded one are a note; *recording_end_ns*: the recorded
    side's last message (log time): a replayed message at the stream's end made of input the live driver read in
    the recording's last TAIL_CUT_NS and after its stream's last recorded message is a note (:func:`after_cut`);
    *decided_before*: a stream of an RC mux that had decided its mode before the recording began
    (:func:`mux_decided_before`): the replayed mux comes out of "no signal" and needs its debounce frames to decide,
    so what is unpaired before the first pair (or in a run of equal messages that begins the stream), and its
    start-up enable write when the recording has none, is a note; *flowing*: the stream was flowing when the
    recording began (:func:`flowing_at_start`): what differs or is unpaired within START_CUT_NS of its first
    message was shaped by what the live driver had read before the cut (a wheel sample waiting for its pair in
    the odometry: the pairs then alternate for a while) and is a note."""
    r = StreamReport(key, len(rec), len(rep))
    if decided_before and rep and not rec:
        r.notes.append(f"{len(rep)} replayed message(s), none recorded: the replayed mux's start-up (its enable line "
                       "requested low), which the live one had done before the recording began")
        return r
    if not rec or not rep:
        r.problems.append("only in the replay" if rep else "not reproduced by the replay")
        return r
    tol = as_tolerances(tolerance)
    channel = key.split(" [", 1)[0]
    system = SYSTEM_FIELDS.get(channel, ())
    keys = content_keys(rec, tol, system), content_keys(rep, tol, system)
    pairs = align(rec, rep, tolerance=tol, skip=system, keys=keys)
    paired = [(p.rec, p.rep) for p in pairs if p.rec is not None and p.rep is not None]
    runs = equal_runs(rec, keys[0]), equal_runs(rep, keys[1])
    rec_of_rep = {j: i for i, j in paired}
    at_edges: list[str] = []
    held_seen: dict[HeldWindow, int] = {}   # differences inside a held-up window, per window
    system_changes = 0   # unpaired messages published for a change of a system-decided field
    changes_used: dict[tuple[int, int], list[int]] = {}   # (id of a side, its run's first index) -> budget
    rec_edge, rep_edge = edge_positions(rec, edge), edge_positions(rep, edge)
    # the partial pairs at the edges (a cut epoch): (recorded, replayed) indexes
    cut_pairs = {(i, j) for i, j in paired
                 if (i in rec_edge or j in rep_edge)
                 and (names := [n for n in differing_fields(rec[i], rep[j], tol) if n not in system])
                 and partial(rec[i], rep[j], names)}
    startup = 0   # replayed start-up writes the recording began after (started_before)
    deciding = 0   # unpaired while the replayed mux decided what the live one had before the cut (decided_before)
    first_decided = next((j for j, b in enumerate(rep) if mux_decided_before([b])), 0) if decided_before else 0
    tail_cut = 0   # replayed messages made of input whose live output the recording ended before
    last_pair = max((k for k, p in enumerate(pairs) if p.kind in ("match", "differ")), default=-1)
    paired_yet = False
    # flowing: the pairs within START_CUT_NS of the stream's start are the cut's (the live driver's state then)
    rec_before, rec_after = recorded_times(pairs, rec, max(rec[-1].t_ns, recording_end_ns or 0))
    settling = {k for k in range(len(pairs)) if rec_before[k] - rec[0].t_ns <= START_CUT_NS} if flowing else set()
    cut_differ = {(pairs[k].rec, pairs[k].rep) for k in settling if pairs[k].kind == "differ"}
    at_start = len(cut_differ)
    for k, p in enumerate(pairs):
        if k in settling and p.kind in ("deleted", "inserted"):
            at_start += 1
            continue
        if p.kind in ("match", "differ"):
            paired_yet = True
            continue
        if started_before and not paired_yet and p.kind == "inserted":
            startup += 1
            continue
        own, index = (rec, p.rec) if p.kind == "deleted" else (rep, p.rep)
        assert index is not None
        if decided_before and (not paired_yet or 0 in runs[0 if p.kind == "deleted" else 1][index]):
            deciding += 1
            continue
        if p.kind == "inserted" and k > last_pair and after_cut(rep[index], rec[-1], recording_end_ns):
            tail_cut += 1
            continue
        if index in (rec_edge if p.kind == "deleted" else rep_edge):
            at_edges.append(p.kind)
            continue
        if rest_of_cut(pairs, k, cut_pairs, rec, rep, tol):
            # the other part of an epoch the cut split in two (its partial pair is beside it)
            at_edges.append(p.kind)
            continue
        # of a run of equal messages the alignment leaves out one of them, not necessarily the one it names (it
        # puts the gap at the run's end): the message may be any of the run's, so the run's times and verdict
        # changes count
        run = runs[0 if p.kind == "deleted" else 1][index]
        if p.kind == "deleted":
            times = [rec[m].t_ns for m in run]
        else:   # between the recorded messages before and after it, or any paired with its run
            # (none after it: up to the recording's end)
            times = [rec_before[k], rec_after[k], *(rec[rec_of_rep[m]].t_ns for m in run if m in rec_of_rep)]
        if _in_held(held, times, held_seen):
            continue
        if system and _system_change_left(own, run, system, changes_used, kept=KEPT_BY_VERDICT.get(channel, ())):
            # published because a pre-arm verdict changed, which the rest of the system decides: where the
            # replay's verdict changes is a note like the verdicts themselves (a timed or device-driven
            # message away from a verdict change still counts)
            system_changes += 1
            continue
        if p.kind == "deleted":
            r.deleted += 1
        else:
            r.inserted += 1
        r.events.append(Event(p.kind, index, rec_before[k]))
    offsets: list[float] = []
    k0 = 0   # the timing reference: the first pair whose replayed message came after the playback began
    if replay_start_ns is not None:
        k0 = next((k for k, (_, j) in enumerate(paired) if rep[j].t_ns >= replay_start_ns), len(paired))
    system_diffs: dict[str, int] = {}
    cut: list[str] = []   # partial messages where the recording cuts the input (module docstring)
    for k, (i, j) in enumerate(paired):
        a, b = rec[i], rep[j]
        names = differing_fields(a, b, tol)
        if system:
            for name in [n for n in names if n in system]:
                system_diffs[name] = system_diffs.get(name, 0) + 1
            names = [n for n in names if n not in system]
        at_edge = i in rec_edge or j in rep_edge
        if names and (i, j) in cut_differ:
            continue   # counted in at_start
        if names and decided_before and j < first_decided:
            deciding += 1   # the replayed mux still at "no signal" beside the live one's decided mode
            continue
        if names and at_edge and partial(a, b, names):
            cut.append(cut_note(a, b, i, start=i < edge or j < edge, origin_ns=origin_ns or rec[0].t_ns))
            continue
        if names and _in_held(held, [a.t_ns], held_seen):
            continue
        if names:
            r.differing += 1
        else:
            r.matched += 1
        for name in names:
            d = r.fields.setdefault(name, FieldDiff(name))
            d.count += 1
            va, vb = a.fields.get(name), b.fields.get(name)
            if isinstance(va, (int, float)) and isinstance(vb, (int, float)) and not isinstance(va, bool):
                if math.isfinite(va) and math.isfinite(vb):
                    d.max_abs = max(d.max_abs, abs(float(va) - float(vb)))
            if d.first is None:
                d.first = (i, va if name != "_type" else a.type_name, vb if name != "_type" else b.type_name)
                d.first_t_ns = a.t_ns
        if rate is not None and k >= k0 and k0 < len(paired):
            i0, j0 = paired[k0]
            offsets.append(abs((b.t_ns - rep[j0].t_ns) / 1e9 * rate - (a.t_ns - rec[i0].t_ns) / 1e9))
    if offsets:
        r.time_p50_s, r.time_max_s = statistics.median(offsets), max(offsets)
        if r.time_max_s > time_tolerance_s:
            r.problems.append(f"timing: a message is {r.time_max_s:.3f} s off its recorded time "
                              f"(tolerance {time_tolerance_s:g} s)")
    if r.differing:
        r.problems.append(f"{r.differing} of {len(paired)} paired messages differ")
    if r.deleted:
        r.problems.append(f"{r.deleted} recorded message(s) not reproduced (deleted)")
    if r.inserted:
        r.problems.append(f"{r.inserted} replayed message(s) not in the recording (inserted)")
    if system_diffs:
        r.notes.append("decided from the rest of the system (pre-arm checks read every service's health), so a "
                       "note: " + ", ".join(f"{name} differs in {n}" for name, n in sorted(system_diffs.items())))
    if system_changes:
        r.notes.append(f"{system_changes} message(s) on one side only, each published for a change of such a "
                       "verdict (a note like the verdicts)")
    if at_edges:
        r.notes.append(f"{len(at_edges)} message(s) without a counterpart among the first or last {edge} of a "
                       "stream (the recording cuts the input there)")
    r.notes.extend(cut)
    if tail_cut:
        r.notes.append(f"{tail_cut} replayed message(s) at the end made of input the live driver read after its "
                       f"last recorded message and in the recording's last {TAIL_CUT_NS / 1e9:g} s: the recording "
                       "ended before their live counterparts were published (the cut at the end)")
    if at_start:
        r.notes.append(f"{at_start} message(s) different or on one side only within {START_CUT_NS / 1e9:g} s of the "
                       "stream's start: the recording began while it flowed, and what the live driver had read before "
                       "the cut (a wheel sample waiting for its pair) shaped its first messages")
    if deciding:
        r.notes.append(f"{deciding} message(s) on one side only or different while the replayed mux decided its mode: "
                       "the recording began after the live mux had decided (its first RC_MODE is not 'no signal'), and "
                       "a mux coming out of 'no signal' needs its debounce frames")
    if startup:
        r.notes.append(f"{startup} replayed start-up write(s) before the first recorded one: the recording began "
                       "after the live driver had started (its first recorded write already drives the output)")
    origin = origin_ns or rec[0].t_ns
    for w, n in held_seen.items():
        if w.to_ns == STOP_WINDOW_END:
            r.notes.append(f"{n} difference(s) after t={(w.from_ns - origin) / 1e9:.2f} s, where {w.service} {w.why}; "
                           "shown, not counted")
            continue
        r.notes.append(f"{n} difference(s) between t={(w.from_ns - origin) / 1e9:.2f} and {(w.to_ns - origin) / 1e9:.2f} s, "
                       f"where the recording machine held {w.service} up ({w.why} in its health); shown, not counted")
    return r


def _in_held(held: Sequence[HeldWindow], times_ns: Sequence[int], seen: dict[HeldWindow, int]) -> bool:
    """Whether one of the log times *times_ns* is in a held-up window (counted once in *seen*)."""
    for w in held:
        if any(w.holds(t) for t in times_ns):
            seen[w] = seen.get(w, 0) + 1
            return True
    return False


def equal_runs(samples: list[Sample], keys: list[Any]) -> list[list[int]]:
    """For each message, the indexes of its run: the messages next to it in its sequence (the stream's, or its
    actuator's in a command stream, PER_ACTUATOR) with the same alignment key, itself included."""
    runs: list[list[int]] = [[] for _ in samples]
    groups: dict[Any, list[int]] = {}
    for k, sample in enumerate(samples):
        groups.setdefault(sample.fields.get(PER_ACTUATOR), []).append(k)
    for ks in groups.values():
        start = 0
        for n in range(1, len(ks) + 1):
            if n == len(ks) or keys[ks[n]] != keys[ks[start]]:
                run = ks[start:n]
                for k in run:
                    runs[k] = run
                start = n
    return runs


# A command stream holds one sequence per actuator, published together (the RC mux's MANUAL_CMD: one message
# per stick output per frame), so its edges are counted per actuator: a cut frame is one message of each.
PER_ACTUATOR = "base.actuator_name"


def edge_positions(samples: list[Sample], edge: int) -> set[int]:
    """Indexes of *samples* among the first or last *edge* of their sequence: of the stream, or of their
    actuator's commands in a command stream (PER_ACTUATOR)."""
    groups: dict[Any, list[int]] = {}
    for k, sample in enumerate(samples):
        groups.setdefault(sample.fields.get(PER_ACTUATOR), []).append(k)
    return {k for ks in groups.values() for k in (ks[:edge] + ks[-edge:] if edge else [])}


def _system_change_left(stream: list[Sample], run: list[int], system: tuple[str, ...],
                        used: dict[tuple[int, int], list[int]], *, kept: tuple[str, ...] = ()) -> bool:
    """True (and taken) when the run of equal messages *run* of *stream* holds a verdict change not yet taken
    by another unpaired message of it: each change is published at once, one message per change at most. A
    change counts where two messages differ in a *system* field and in none of *kept* (KEPT_BY_VERDICT).
    *used*: per run, [its changes, those taken] (counted once per run)."""
    key = (id(stream), run[0] if run else -1)
    budget = used.get(key)
    if budget is None:
        changes = sum(1 for k in range(max(0, run[0] - 1), min(len(stream) - 1, run[-1] + 1))
                      if _differs(stream[k], stream[k + 1], system) and not _differs(stream[k], stream[k + 1], kept))
        budget = used[key] = [changes, 0]
    if budget[1] >= budget[0]:
        return False
    budget[1] += 1
    return True


def _differs(a: Sample, b: Sample, names: tuple[str, ...]) -> bool:
    return any(not values_equal(a.fields.get(n), b.fields.get(n), 0.0) for n in names)
