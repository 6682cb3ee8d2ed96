"""``u2sa replay --compare``: the replayed outputs against the recorded ones, stream by stream.

A *stream* is one channel from one source service (``STATE_INFO [gps]``): only the
services the replay ran are compared, and never the contract channels (``U2SA_*``: health
carries uptime and CPU) or raw device I/O (``RAW.*``). For each stream:

- counts: recorded and replayed messages. A stream of a service the recording has nothing
  from at all (it was not running) is shown as ``new``, with nothing to compare. A
  recording cuts its devices' input at both ends (the recorder starts and stops while
  drivers run), so up to ``edge`` messages at each end of a stream may go unmatched; they
  are reported as notes, more is a difference.
  The two sequences are aligned at the start by trying the skips up to ``edge`` on either
  side and keeping the one that matches best.
- fields: every field from ``enumerate_fields`` except the header's ``timestamp_us`` and
  ``sequence`` (and ``ignore`` patterns), floats equal within ``tolerance`` (absolute, or
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
they are compared as states over time: each replayed message's time is mapped onto the
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
"""

from __future__ import annotations

import bisect
import fnmatch
import math
import statistics
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from u2sa_hw.channels import base_type
from u2sa_hw.messages import REGISTRY, MalformedMessage, enumerate_fields
from u2sa_hw.recording.log_reader import LogFile

from hil.player import header_source

HEADER_FIELDS = ("*header.timestamp_us", "*header.sequence")
STATE_CHANNELS = ("RC_MODE", "MANUAL_CMD")         # published on a timer and on every change
# Fields a service decides from the whole system's state (the RC mux's pre-arm checks read every
# service's health), which a driver-level replay does not reproduce: a difference is a note.
SYSTEM_FIELDS: dict[str, tuple[str, ...]] = {
    "RC_MODE": ("autonomy_enabled", "armed", "hold", "blocked_by", "select_mismatch"),
}
OUTPUT_RAW_TYPES = ("RawGpioWrite", "RawPwmWrite")  # raw records of what a driver drives
ALIGN_WINDOW = 10
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


def differing_fields(a: Sample, b: Sample, tolerance: float) -> list[str]:
    """Names of the fields that differ (``_type`` when the types do)."""
    if a.type_name != b.type_name:
        return ["_type"]
    names = sorted(set(a.fields) | set(b.fields))
    return [n for n in names if not values_equal(a.fields.get(n), b.fields.get(n), tolerance)]


@dataclass
class FieldDiff:
    """One field that differs in some messages of a stream."""

    name: str
    count: int = 0
    max_abs: float = 0.0
    first: tuple[int, Any, Any] | None = None   # (index, recorded, replayed)


@dataclass
class StreamReport:
    """The comparison of one stream."""

    key: str
    recorded: int
    replayed: int
    matched: int = 0
    differing: int = 0
    head_skipped: tuple[int, int] = (0, 0)        # (recorded, replayed) unmatched at the start
    tail_unmatched: tuple[int, int] = (0, 0)      # ... and at the end
    fields: dict[str, FieldDiff] = field(default_factory=dict)
    time_p50_s: float | None = None
    time_max_s: float | None = None
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when nothing differs beyond the tolerances."""
        return not self.problems


def align(rec: list[Sample], rep: list[Sample], *, edge: int, tolerance: float) -> tuple[int, int]:
    """The (recorded, replayed) head skips, each up to *edge*, under which the next messages match best."""
    best: tuple[tuple[int, int], tuple[int, int]] | None = None
    for i in range(min(edge, len(rec)) + 1):
        for j in range(min(edge, len(rep)) + 1):
            n = min(ALIGN_WINDOW, len(rec) - i, len(rep) - j)
            bad = ALIGN_WINDOW + 1 if n <= 0 else sum(
                bool(differing_fields(rec[i + k], rep[j + k], tolerance)) for k in range(n))
            score = (bad, i + j)
            if best is None or score < best[0]:
                best = (score, (i, j))
    return best[1] if best else (0, 0)


def compare_stream(key: str, rec: list[Sample], rep: list[Sample], *, tolerance: float, edge: int,
                   rate: float | None, time_tolerance_s: float, replay_start_ns: int | None = None) -> StreamReport:
    """Compare one stream (see the module docstring); *replay_start_ns*: when the playback began."""
    r = StreamReport(key, len(rec), len(rep))
    if not rec or not rep:
        r.problems.append("only in the replay" if rep else "not reproduced by the replay")
        return r
    i0, j0 = align(rec, rep, edge=edge, tolerance=tolerance)
    n = min(len(rec) - i0, len(rep) - j0)
    r.head_skipped, r.matched = (i0, j0), n
    r.tail_unmatched = (len(rec) - i0 - n, len(rep) - j0 - n)
    offsets: list[float] = []
    k0 = 0   # the timing reference: the first pair whose replayed message came after the playback began
    if replay_start_ns is not None:
        k0 = next((k for k in range(n) if rep[j0 + k].t_ns >= replay_start_ns), n)
    for k in range(n):
        a, b = rec[i0 + k], rep[j0 + k]
        names = differing_fields(a, b, tolerance)
        if names:
            r.differing += 1
        for name in names:
            d = r.fields.setdefault(name, FieldDiff(name))
            d.count += 1
            va, vb = a.fields.get(name), b.fields.get(name)
            if isinstance(va, (int, float)) and isinstance(vb, (int, float)) and not isinstance(va, bool):
                if math.isfinite(va) and math.isfinite(vb):
                    d.max_abs = max(d.max_abs, abs(float(va) - float(vb)))
            if d.first is None:
                d.first = (k, va if name != "_type" else a.type_name, vb if name != "_type" else b.type_name)
        if rate is not None and k >= k0:
            rec_s = (a.t_ns - rec[i0 + k0].t_ns) / 1e9
            rep_s = (b.t_ns - rep[j0 + k0].t_ns) / 1e9 * rate
            offsets.append(abs(rep_s - rec_s))
    if offsets:
        r.time_p50_s, r.time_max_s = statistics.median(offsets), max(offsets)
        if r.time_max_s > time_tolerance_s:
            r.problems.append(f"timing: a message is {r.time_max_s:.3f} s off its recorded time "
                              f"(tolerance {time_tolerance_s:g} s)")
    if r.differing:
        r.problems.append(f"{r.differing} of {n} matched messages differ")
    for where, (a_n, b_n) in (("start", r.head_skipped), ("end", r.tail_unmatched)):
        for count, what in ((a_n, "recorded message(s) not reproduced"), (b_n, "replayed message(s) not recorded")):
            if not count:
                continue
            text = f"{count} {what} at the {where}"
            (r.notes if count <= edge else r.problems).append(
                text + (" (the recording cuts the input there)" if count <= edge else ""))
    return r


def _missing_fields(s: Sample, times: list[int], others: list[Sample], *, window_ns: int,
                    tolerance: float) -> tuple[list[str], Sample | None]:
    """Fields of *s* whose value no message of *others* (sorted by time) had within *window_ns* of it,
    counting the one then held; and the nearest of those messages."""
    lo = bisect.bisect_left(times, s.t_ns - window_ns)
    hi = bisect.bisect_right(times, s.t_ns + window_ns)
    near = others[max(0, lo - 1):hi]
    if not near:
        return ["_type"], None
    nearest = min(near, key=lambda o: abs(o.t_ns - s.t_ns))
    missing = [] if any(o.type_name == s.type_name for o in near) else ["_type"]
    missing += [name for name, value in s.fields.items()
                if not any(values_equal(value, o.fields.get(name), tolerance) for o in near)]
    return missing, nearest


def _elements(fields: dict[str, Any]) -> dict[str, Any]:
    """*fields* with every list split into its elements (``pulse_us[0]``, ...): each element is a state of its own."""
    out: dict[str, Any] = {}
    for name, value in fields.items():
        if isinstance(value, (list, tuple)):
            out[f"{name}.len"] = len(value)
            out.update((f"{name}[{i}]", v) for i, v in enumerate(value))
        else:
            out[name] = value
    return out


def compare_states(key: str, rec: list[Sample], rep: list[Sample], *, tolerance: float, edge: int,
                   time_tolerance_s: float, start_ns: int, end_ns: int, rate: float,
                   replay_start_ns: int) -> StreamReport:
    """Compare a state stream over time (see the module docstring)."""
    rec = [Sample(s.t_ns, s.type_name, _elements(s.fields)) for s in rec]
    mapped = sorted((Sample(start_ns + int((s.t_ns - replay_start_ns) * rate), s.type_name, _elements(s.fields))
                     for s in rep), key=lambda s: s.t_ns)
    # only while the recorded stream ran: before it the recorded service was not up (or not recorded yet)
    first, last = (max(start_ns, rec[0].t_ns), min(end_ns, rec[-1].t_ns)) if rec else (start_ns, end_ns)
    inside = [s for s in mapped if first <= s.t_ns <= last]
    r = StreamReport(key, len(rec), len(inside))
    r.notes.append("a state stream: compared over time (every field value found on the other side within "
                   f"{time_tolerance_s:g} s), not message by message")
    if not rec or not inside:
        r.problems.append("only in the replay" if inside else "not reproduced by the replay")
        return r
    window = int(time_tolerance_s * 1e9)
    sides = ((rec, mapped, "recorded"), (inside, rec, "replayed"))
    unmatched = {"recorded": 0, "replayed": 0}
    at_edges = 0
    system = SYSTEM_FIELDS.get(key.split(" [", 1)[0], ())
    decided: dict[str, int] = {}
    for samples, others, side in sides:
        times = [o.t_ns for o in others]
        for i, s in enumerate(samples):
            missing, nearest = _missing_fields(s, times, others, window_ns=window, tolerance=tolerance)
            for name in [m for m in missing if m in system]:
                decided[name] = decided.get(name, 0) + 1
            missing = [m for m in missing if m not in system]
            if not missing:
                if side == "recorded":
                    r.matched += 1
                continue
            if i < edge or i >= len(samples) - edge:
                at_edges += 1
                continue
            unmatched[side] += 1
            for name in missing:
                d = r.fields.setdefault(name, FieldDiff(name))
                d.count += 1
                if d.first is None:
                    mine = s.type_name if name == "_type" else s.fields.get(name)
                    other = None if nearest is None else (nearest.type_name if name == "_type"
                                                          else nearest.fields.get(name))
                    d.first = (i, mine, other) if side == "recorded" else (i, other, mine)
    r.differing = unmatched["recorded"] + unmatched["replayed"]
    if r.differing:
        r.problems.append(f"{unmatched['recorded']} recorded and {unmatched['replayed']} replayed messages hold a "
                          f"field value the other side did not have within {time_tolerance_s:g} s")
    if at_edges:
        r.notes.append(f"{at_edges} message(s) at the start or end of the window without a counterpart "
                       "(the recording cuts the input there)")
    if decided:
        r.notes.append("decided from the whole system's health, which a driver-level replay does not reproduce "
                       f"(not a difference): {', '.join(f'{n} in {c}' for n, c in sorted(decided.items()))}")
    return r


@dataclass
class CompareReport:
    """Every stream's comparison."""

    recorded: Path
    replayed: Path
    streams: list[StreamReport]
    tolerance: float
    timed: bool

    @property
    def ok(self) -> bool:
        """True when no stream differs."""
        return all(s.ok for s in self.streams)

    def format(self) -> str:
        """The printed report."""
        lines = [f"compare: recorded {self.recorded} vs replayed {self.replayed} (tolerance {self.tolerance:g}; "
                 f"header timestamp and sequence not compared{'' if self.timed else '; timing not checked (--fast)'})",
                 f"{'STREAM':32} {'RECORDED':>8} {'REPLAYED':>8} {'MATCHED':>7} {'DIFFER':>6} "
                 f"{'TIME p50/max s':>15}  RESULT"]
        for s in self.streams:
            timing = "-" if s.time_max_s is None else f"{s.time_p50_s:.3f}/{s.time_max_s:.3f}"
            result = "DIFFERENT" if not s.ok else "same" if s.recorded else "new"
            lines.append(f"{s.key:32} {s.recorded:>8} {s.replayed:>8} {s.matched:>7} {s.differing:>6} "
                         f"{timing:>15}  {result}")
        for s in self.streams:
            for problem in s.problems:
                lines.append(f"  {s.key}: {problem}")
            for d in sorted(s.fields.values(), key=lambda d: -d.count)[:SHOWN_FIELDS]:
                k, va, vb = d.first or (0, None, None)
                size = f", max |d| {d.max_abs:.6g}" if d.max_abs else ""
                lines.append(f"    {d.name}: differs in {d.count} of {s.matched}{size}; first at #{k}: "
                             f"recorded {va!r}, replayed {vb!r}")
            if len(s.fields) > SHOWN_FIELDS:
                lines.append(f"    ... and {len(s.fields) - SHOWN_FIELDS} more fields")
            for note in s.notes:
                lines.append(f"  {s.key}: note: {note}")
        bad = sum(not s.ok for s in self.streams)
        if not self.streams:
            lines.append("result: no streams to compare (the replayed services published nothing, "
                         "and the recording has nothing from them)")
        else:
            lines.append(f"result: {'no differences' if not bad else f'{bad} of {len(self.streams)} streams differ'}")
        return "\n".join(lines)


def compare_logs(recorded: Path | str, replayed: Path | str, *, services: set[str], start_ns: int | None = None,
                 end_ns: int | None = None, rate: float | None = 1.0, tolerance: float = 1e-6, edge: int = 1,
                 time_tolerance_s: float = 0.5, ignore: tuple[str, ...] = (),
                 replay_start_ns: int | None = None) -> CompareReport:
    """Compare the streams of *services* in *recorded* (within the window) and *replayed*; ``rate=None``: no timing.

    *replay_start_ns*: the wall-clock time the playback began (log time *start_ns* was played
    then); with a rate and the window it lets state channels be compared over time.
    """
    rec = load_streams(recorded, sources=services, start_ns=start_ns, end_ns=end_ns, ignore=ignore)
    rep = load_streams(replayed, sources=services, ignore=ignore)
    reports = []
    for key in sorted(set(rec) | set(rep)):
        a, b = rec.get(key, []), rep.get(key, [])
        timed = rate is not None and replay_start_ns is not None and start_ns is not None and end_ns is not None
        if timed and key.split(" [", 1)[0] in STATE_CHANNELS:
            reports.append(compare_states(key, a, b, tolerance=tolerance, edge=edge, time_tolerance_s=time_tolerance_s,
                                          start_ns=start_ns, end_ns=end_ns, rate=rate, replay_start_ns=replay_start_ns))
        else:
            reports.append(compare_stream(key, a, b, tolerance=tolerance, edge=edge, rate=rate,
                                          time_tolerance_s=time_tolerance_s, replay_start_ns=replay_start_ns))
    recorded_sources = {key.rsplit(" [", 1)[1] for key in rec}
    for r in reports:
        if not r.recorded and r.key.rsplit(" [", 1)[1] not in recorded_sources:
            # a service that was not running (or not recorded) in the log: nothing to compare with
            r.problems.clear()
            r.notes.append("the recording has nothing from this service to compare with")
    return CompareReport(Path(recorded), Path(replayed), reports, tolerance, rate is not None)
