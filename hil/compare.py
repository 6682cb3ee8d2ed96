"""``u2sa replay --compare``: the replayed outputs against the recorded ones, stream by stream.

A *stream* is one channel from one source service (``STATE_INFO [gps]``): only the
services the replay ran are compared, and never the contract channels (``U2SA_*``: health
carries uptime and CPU) or raw device I/O (``RAW.*``). For each stream:

- alignment (hil/stream_align.py): the two streams are paired as ``diff`` pairs lines, in
  order and by content, so one extra or missing message is one *insertion* or *deletion*
  (reported with its time in the recording) and the rest still pair. Paired messages
  *match* or *differ* in named fields. A stream of a service the recording has nothing
  from at all (it was not running) is shown as ``new``, with nothing to compare. A
  recording cuts its devices' input at both ends (the recorder starts and stops while
  drivers run), so insertions or deletions among the first or last ``edge`` messages of a
  stream are notes; elsewhere they are differences. So is a *partial* message there: a pair
  among the first or last ``edge`` whose only differences are fields one side holds and the
  other does not (``presence_vector`` with them), every field both hold being equal. That is
  what a cut epoch gives (the recording begins after the live driver read a burst's first
  sentences: the live fix holds position and velocity, the replayed one only the velocity of
  the sentences recorded; or it ends before the burst's last ones): a note naming the stream,
  the message and the cut, never counted as matched or different. A value that differs, at an
  edge or anywhere, and a partial message away from the edges, are differences.
- fields: every field from ``enumerate_fields`` except the header's ``timestamp_us`` and
  ``sequence`` (and ``ignore`` patterns), floats equal within their field's tolerance
  (:class:`Tolerances`: a default and per-field globs, from ``--tolerances FILE``; absolute, or
  relative 1e-9), everything else exactly.
- timing: each message's time since the stream's first, replayed (times the rate) against
  recorded; the median and largest offset are shown and a largest offset above
  ``time_tolerance_s`` is a difference. Not checked for ``--fast`` replays, which have no clock.
  Messages a replayed service published before the playback began (while it started) are
  not timed: the first message at or after the playback's start is the reference.

Raw device I/O is left out except the records of what a driver *drives*: ``RawGpioWrite``
and ``RawPwmWrite`` (a GPIO or PWM driver's outputs), compared like any stream under
``RAW.<device> [service]``.

State channels (``STATE_CHANNELS``: ``RC_MODE``, ``MANUAL_CMD``) are published on a timer as well as on
every change, so which messages exist depends on the timer's phase. With a clock (``--rate``)
they are compared as states over time (hil/compare_states.py): each replayed message's time is mapped onto the
log's clock (the playback started at log time ``start_ns``), and every field value (each
element of a list on its own) of every message must also be found on the other side within
``time_tolerance_s`` of it (the state then held counts). The first and last ``edge``
messages of each side may miss (the input starts and ends there); they are notes. Replayed
messages from before the recorded stream's first message or after its last are not compared
(the recorded service was not running, or not recorded, then; after the input ends a driver
reacts to its end).

``SYSTEM_FIELDS`` are what a service decides from the rest of the system, not from its
device: the RC mux's ``autonomy_enabled``, ``armed``, ``hold``, ``blocked_by`` (its pre-arm
checks read every service's health) and ``select_mismatch`` (the recorded select read-back
against the replay's own enable decision). They are compared, and a difference is a note.
They do not steer the alignment, and a message on one side only that was published for a
change of one of them (one differs between it and the stream's message before or after it)
is a note too: on a loaded machine the live mux read the other services' health in another
order than the recorder wrote it, so its verdict may change a few messages apart from the
replay's. A timed or device-driven message away from a verdict change still counts.
"""

from __future__ import annotations

import fnmatch
import math
import statistics
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence, Union

from u2sa_hw.channels import base_type
from u2sa_hw.messages import ABSENT, REGISTRY, MalformedMessage, enumerate_fields
from u2sa_hw.recording.log_reader import LogFile

from u2sa_hw.hil.held_up import HeldWindow
from u2sa_hw.hil.player import header_source
from u2sa_hw.hil.stream_align import Pair, align_streams, content_key

HEADER_FIELDS = ("*header.timestamp_us", "*header.sequence")
STATE_CHANNELS = ("RC_MODE", "MANUAL_CMD")         # published on a timer and on every change
# Fields a service decides from the whole system's state (the RC mux's pre-arm checks read every
# service's health), which a driver-level replay does not reproduce: a difference is a note.
SYSTEM_FIELDS: dict[str, tuple[str, ...]] = {
    "RC_MODE": ("autonomy_enabled", "armed", "hold", "blocked_by", "select_mismatch"),
}
OUTPUT_RAW_TYPES = ("RawGpioWrite", "RawPwmWrite")  # raw records of what a driver drives
SHOWN_FIELDS = 8


@dataclass(frozen=True)
class Sample:
    """One message of a stream: log time, type and its comparable fields."""

    t_ns: int
    type_name: str
    fields: dict[str, Any]


def load_streams(path: Path | str, *, sources: set[str], start_ns: int | None = None, end_ns: int | None = None,
                 ignore: tuple[str, ...] = ()) -> dict[str, list[Sample]]:
    """``"CHANNEL [source]"`` -> samples, for messages from *sources* within the window."""
    patterns = (*HEADER_FIELDS, *ignore)
    streams: dict[str, list[Sample]] = {}
    for m in LogFile(path).messages():
        if m.channel.startswith("U2SA_") or (m.channel.startswith("RAW.") and m.type_name not in OUTPUT_RAW_TYPES):
            continue
        if (start_ns is not None and m.log_time_ns < start_ns) or (end_ns is not None and m.log_time_ns > end_ns):
            continue
        try:
            msg, _ = REGISTRY.decode(m.data, base_type(m.channel))
        except MalformedMessage:
            continue
        source = header_source(msg)
        if source not in sources:
            continue
        fields = {k: v for k, v in enumerate_fields(msg) if not any(fnmatch.fnmatchcase(k, p) for p in patterns)}
        streams.setdefault(f"{m.channel} [{source}]", []).append(Sample(m.log_time_ns, type(msg).__name__, fields))
    return streams


class Tolerances:
    """Float tolerance per field: a default and ``glob -> tolerance`` overrides (first match wins).

    A file (``--tolerances FILE``, TOML) holds ``default = 1e-6``, a ``[fields]`` table of
    glob patterns (``"*sigma*" = 1e-3``, ``"x" = 0.01``) and ``ignore = ["psi_sigma"]``.
    """

    def __init__(self, default: float = 1e-6, fields: dict[str, float] | None = None,
                 ignore: tuple[str, ...] = ()) -> None:
        self.default = float(default)
        self.fields = dict(fields or {})
        self.ignore = tuple(ignore)
        self._cache: dict[str, float] = {}

    def of(self, name: str) -> float:
        """The tolerance of the field *name*."""
        tol = self._cache.get(name)
        if tol is None:
            tol = next((t for pattern, t in self.fields.items() if fnmatch.fnmatchcase(name, pattern)), self.default)
            self._cache[name] = tol
        return tol

    @classmethod
    def load(cls, path: Path | str, *, default: float = 1e-6, ignore: tuple[str, ...] = ()) -> "Tolerances":
        """Read a tolerance file; ValueError naming the file, the key and the fix when it is wrong."""
        import tomllib
        try:
            data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
        except OSError as exc:
            raise ValueError(f"{path}: cannot read the tolerance file: {exc.strerror or exc}") from None
        except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise ValueError(f"{path}: not a TOML tolerance file ({exc}); "
                             'expected e.g. default = 1e-6, [fields] "x" = 0.01, ignore = ["psi_sigma"]') from None
        unknown = set(data) - {"default", "fields", "ignore"}
        if unknown:
            raise ValueError(f"{path}: unknown key(s) {', '.join(sorted(unknown))}; allowed: default, fields, ignore")

        def number(key: str, value: Any) -> float:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ValueError(f"{path}: {key} = {value!r}: a tolerance is a finite number >= 0")
            return float(value)

        fields = data.get("fields", {})
        if not isinstance(fields, dict):
            raise ValueError(f"{path}: fields must be a table of \"glob\" = tolerance")
        ignored = data.get("ignore", [])
        if not isinstance(ignored, list) or not all(isinstance(g, str) for g in ignored):
            raise ValueError(f"{path}: ignore must be a list of field globs")
        return cls(number("default", data.get("default", default)),
                   {str(k): number(f"fields.{k}", v) for k, v in fields.items()}, (*ignore, *ignored))


ToleranceLike = Union[float, Tolerances]


def _tolerances(t: ToleranceLike) -> Tolerances:
    return t if isinstance(t, Tolerances) else Tolerances(t)


def values_equal(a: Any, b: Any, tolerance: float) -> bool:
    """Floats within *tolerance* (NaN equals NaN), lists element-wise, the rest exactly."""
    if isinstance(a, float) or isinstance(b, float):
        try:
            fa, fb = float(a), float(b)
        except (TypeError, ValueError):
            return False
        if math.isnan(fa) or math.isnan(fb):
            return math.isnan(fa) and math.isnan(fb)
        return math.isclose(fa, fb, rel_tol=1e-9, abs_tol=tolerance)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(values_equal(x, y, tolerance) for x, y in zip(a, b))
    return a == b


def differing_fields(a: Sample, b: Sample, tolerance: ToleranceLike) -> list[str]:
    """Names of the fields that differ (``_type`` when the types do)."""
    if a.type_name != b.type_name:
        return ["_type"]
    tol = _tolerances(tolerance)
    names = sorted(set(a.fields) | set(b.fields))
    return [n for n in names if not values_equal(a.fields.get(n), b.fields.get(n), tol.of(n))]


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


def align(rec: list[Sample], rep: list[Sample], *, tolerance: ToleranceLike,
          skip: tuple[str, ...] = ()) -> list[Pair]:
    """Pair the two streams' messages in order (hil/stream_align.py): match, differ, deleted, inserted.

    Fields in *skip* (the stream's ``SYSTEM_FIELDS``) do not steer the pairing: a difference there is a note.
    """
    tol = _tolerances(tolerance)

    def own(fields: dict[str, Any]) -> dict[str, Any]:
        return {n: v for n, v in fields.items() if n not in skip} if skip else fields

    rec_keys = [content_key(s.type_name, own(s.fields), tol.of) for s in rec]
    rep_keys = [content_key(s.type_name, own(s.fields), tol.of) for s in rep]

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
                   started_before: bool = False) -> StreamReport:
    """Compare one stream (see the module docstring); *replay_start_ns*: when the playback began; *origin_ns*:
    the log time notes count seconds from (default the stream's first recorded message); *held*: where the
    recording machine held the stream's service up (hil/held_up.py): what differs there is a note;
    *started_before*: the recording began after the stream's driver started (:func:`begun_after_start`),
    so the replayed start-up writes before the first recorded one are a note."""
    r = StreamReport(key, len(rec), len(rep))
    if not rec or not rep:
        r.problems.append("only in the replay" if rep else "not reproduced by the replay")
        return r
    tol = _tolerances(tolerance)
    system = SYSTEM_FIELDS.get(key.split(" [", 1)[0], ())
    pairs = align(rec, rep, tolerance=tol, skip=system)
    paired = [(p.rec, p.rep) for p in pairs if p.rec is not None and p.rep is not None]
    at_edges: list[str] = []
    held_seen: dict[HeldWindow, int] = {}   # differences inside a held-up window, per window
    system_changes = 0   # unpaired messages published for a change of a system-decided field
    rec_edge, rep_edge = edge_positions(rec, edge), edge_positions(rep, edge)
    # the partial pairs at the edges (a cut epoch): (recorded, replayed) indexes
    cut_pairs = {(i, j) for i, j in paired
                 if (i in rec_edge or j in rep_edge)
                 and (names := [n for n in differing_fields(rec[i], rep[j], tol) if n not in system])
                 and partial(rec[i], rep[j], names)}
    last_rec_t = rec[0].t_ns
    startup = 0   # replayed start-up writes the recording began after (started_before)
    paired_yet = False
    for k, p in enumerate(pairs):
        if p.rec is not None:
            last_rec_t = rec[p.rec].t_ns
        if p.kind in ("match", "differ"):
            paired_yet = True
            continue
        if started_before and not paired_yet and p.kind == "inserted":
            startup += 1
            continue
        own, index = (rec, p.rec) if p.kind == "deleted" else (rep, p.rep)
        assert index is not None
        if index in (rec_edge if p.kind == "deleted" else rep_edge):
            at_edges.append(p.kind)
            continue
        if _rest_of_cut(pairs, k, cut_pairs, rec, rep, tol):
            # the other part of an epoch the cut split in two (its partial pair is beside it)
            at_edges.append(p.kind)
            continue
        if _in_held(held, last_rec_t, held_seen):
            continue
        if system and _at_system_change(own, index, system):
            # published because a pre-arm verdict changed, which the rest of the system decides: where the
            # replay's verdict changes is a note like the verdicts themselves (a timed or device-driven
            # message away from a verdict change still counts)
            system_changes += 1
            continue
        if p.kind == "deleted":
            r.deleted += 1
        else:
            r.inserted += 1
        r.events.append(Event(p.kind, index, last_rec_t))
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
        if names and at_edge and partial(a, b, names):
            cut.append(_cut_note(a, b, i, start=i < edge or j < edge, origin_ns=origin_ns or rec[0].t_ns))
            continue
        if names and _in_held(held, a.t_ns, held_seen):
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
    if startup:
        r.notes.append(f"{startup} replayed start-up write(s) before the first recorded one: the recording began "
                       "after the live driver had started (its first recorded write already drives the output)")
    origin = origin_ns or rec[0].t_ns
    for w, n in held_seen.items():
        r.notes.append(f"{n} difference(s) between t={(w.from_ns - origin) / 1e9:.2f} and {(w.to_ns - origin) / 1e9:.2f} s, "
                       f"where the recording machine held {w.service} up ({w.why} in its health); shown, not counted")
    return r


def begun_after_start(rec: list[Sample]) -> bool:
    """True for a PWM output stream whose first recorded write already has the output enabled: a driver
    starts its outputs disabled (duty 0, then neutral) before it enables them, so the recording began
    after the live driver's start-up, which the replayed driver does again."""
    return bool(rec) and rec[0].type_name == "RawPwmWrite" and bool(rec[0].fields.get("enabled"))


def _in_held(held: Sequence[HeldWindow], t_ns: int, seen: dict[HeldWindow, int]) -> bool:
    """Whether log time *t_ns* is in a held-up window (counted in *seen*)."""
    for w in held:
        if w.holds(t_ns):
            seen[w] = seen.get(w, 0) + 1
            return True
    return False


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


def partial(a: Sample, b: Sample, names: list[str]) -> bool:
    """True when *a* and *b* differ only in which fields they hold (*names*: the differing fields): each
    is ``presence_vector`` or a field one of them leaves out, and at least one is such a field. Every
    field both hold is then equal: one message holds part of the other's epoch."""
    if a.type_name != b.type_name:
        return False
    held = [n for n in names if n != "presence_vector"]
    return bool(held) and all(a.fields.get(n) is ABSENT or b.fields.get(n) is ABSENT for n in held)


def _rest_of_cut(pairs: list[Pair], k: int, cut_pairs: set[tuple[int, int]], rec: list[Sample],
                 rep: list[Sample], tol: Tolerances) -> bool:
    """True when the unpaired message ``pairs[k]`` is beside a partial pair at a cut and holds part of the
    same epoch: every field it holds is held, equal, by that pair's message on the other side."""
    p = pairs[k]
    for q in (pairs[k - 1] if k else None, pairs[k + 1] if k + 1 < len(pairs) else None):
        if q is None or q.rec is None or q.rep is None or (q.rec, q.rep) not in cut_pairs:
            continue
        mine, other = (rec[p.rec], rep[q.rep]) if p.kind == "deleted" else (rep[p.rep], rec[q.rec])  # type: ignore[index]
        if mine.type_name == other.type_name and all(
                other.fields.get(n) is not ABSENT and values_equal(v, other.fields.get(n), tol.of(n))
                for n, v in mine.fields.items() if v is not ABSENT and n != "presence_vector"):
            return True
    return False


def _cut_note(a: Sample, b: Sample, index: int, *, start: bool, origin_ns: int) -> str:
    """The note for a partial message at a cut: which side holds which fields, and where the cut is."""
    only_rec = [n for n, v in a.fields.items() if v is not ABSENT and b.fields.get(n) is ABSENT]
    only_rep = [n for n, v in b.fields.items() if v is not ABSENT and a.fields.get(n) is ABSENT]

    def names(fields: list[str]) -> str:
        return ", ".join(fields[:SHOWN_FIELDS]) + (f" (+{len(fields) - SHOWN_FIELDS})" if len(fields) > SHOWN_FIELDS
                                                   else "")

    held = "; ".join(part for part in (f"only the recorded one holds {names(only_rec)}" if only_rec else "",
                                       f"only the replayed one holds {names(only_rep)}" if only_rep else "") if part)
    where = ("at the start of the stream: the recording begins inside the epoch or burst of input this message "
             "was made of (the live driver had read its first part before), or the live driver, held up as it "
             "started, read it in two parts with a gap the log cannot tell from a silence" if start else
             "at the end of the stream: the recording ends inside the epoch or burst of input this message was "
             "made of")
    return (f"cut: recorded #{index} at t={(a.t_ns - origin_ns) / 1e9:.3f} s and its replay hold part of one epoch each ({held}; every "
            f"field both hold is equal), {where}: a note, not a difference")


def _at_system_change(stream: list[Sample], index: int, system: tuple[str, ...]) -> bool:
    """True when a system-decided field changes between message *index* and the one before or after it
    (of two messages published for one verdict change, the alignment may leave either unpaired)."""
    here = stream[index].fields
    return any(0 <= k < len(stream) and any(not values_equal(here.get(n), stream[k].fields.get(n), 0.0)
                                            for n in system)
               for k in (index - 1, index + 1))


def compare_logs(recorded: Path | str, replayed: Path | str, *, services: set[str], start_ns: int | None = None,
                 end_ns: int | None = None, rate: float | None = 1.0, tolerance: ToleranceLike = 1e-6, edge: int = 1,
                 time_tolerance_s: float = 0.5, ignore: tuple[str, ...] = (),
                 replay_start_ns: int | None = None, pilot: Any = None,
                 held: Mapping[str, Sequence[HeldWindow]] | None = None) -> "CompareReport":
    """Compare the streams of *services* in *recorded* (within the window) and *replayed*; ``rate=None``: no timing.

    *replay_start_ns*: the wall-clock time the playback began (log time *start_ns* was played
    then); with a rate and the window it lets state channels be compared over time.
    *pilot*: the check of the recorded pilot messages (u2sa_hw.recording.pilot_check.PilotCheck,
    ``ReplayResult.pilot``): reported, and a message that fails it is a finding.
    The recorded pilot trailers never reach the comparison (the log reader cuts them off).
    *held*: service -> the windows where the recording machine held it up
    (u2sa_hw.hil.held_up, ``ReplayPlan.held_windows``); what differs there is a note.
    """
    from u2sa_hw.hil.compare_report import CompareReport
    from u2sa_hw.hil.compare_states import compare_states

    tol = _tolerances(tolerance)
    ignore = (*ignore, *tol.ignore)
    rec = load_streams(recorded, sources=services, start_ns=start_ns, end_ns=end_ns, ignore=ignore)
    rep = load_streams(replayed, sources=services, ignore=ignore)
    origin = start_ns if start_ns is not None else min((v[0].t_ns for v in rec.values() if v), default=0)
    windows = held or {}
    reports = []
    for key in sorted(set(rec) | set(rep)):
        a, b = rec.get(key, []), rep.get(key, [])
        timed = rate is not None and replay_start_ns is not None and start_ns is not None and end_ns is not None
        if timed and key.split(" [", 1)[0] in STATE_CHANNELS:
            reports.append(compare_states(key, a, b, tolerance=tol, edge=edge, time_tolerance_s=time_tolerance_s,
                                          start_ns=start_ns, end_ns=end_ns, rate=rate, replay_start_ns=replay_start_ns))
        else:
            reports.append(compare_stream(key, a, b, tolerance=tol, edge=edge, rate=rate,
                                          time_tolerance_s=time_tolerance_s, replay_start_ns=replay_start_ns,
                                          origin_ns=origin, held=windows.get(key.rsplit(" [", 1)[1][:-1], ()),
                                          started_before=begun_after_start(a)))
    recorded_sources = {key.rsplit(" [", 1)[1] for key in rec}
    for r in reports:
        if not r.recorded and r.key.rsplit(" [", 1)[1] not in recorded_sources:
            # a service that was not running (or not recorded) in the log: nothing to compare with
            r.problems.clear()
            r.notes.append("the recording has nothing from this service to compare with")
    return CompareReport(Path(recorded), Path(replayed), reports, tol, rate is not None, origin, pilot)
