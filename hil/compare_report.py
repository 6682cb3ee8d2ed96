"""The result of ``u2sa replay --compare``: a table per stream, the first differences, one summary line, JSON.

Times in the report are seconds from the start of the compared window of the recording
(its first message), so a difference can be found in the log with ``u2sa log echo``.

The check of the recorded pilot messages (u2sa_hw.recording.pilot_check) is a line of the report
and a finding when a message fails it: the comparison is then not OK, whatever the streams say.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from u2sa_hw.hil.compare_stream import StreamReport
from u2sa_hw.hil.compare_values import Tolerances

SHOWN_FIELDS = 8
SHOWN_EVENTS = 5


def _json_value(v: Any) -> Any:
    """*v* made JSON-safe (non-finite floats as strings)."""
    if isinstance(v, float) and not math.isfinite(v):
        return repr(v)
    if isinstance(v, (list, tuple)):
        return [_json_value(x) for x in v]
    if isinstance(v, (bytes, bytearray)):
        return v.hex()
    return v


@dataclass
class CompareReport:
    """Every stream's comparison."""

    recorded: Path
    replayed: Path
    streams: list[StreamReport]
    tolerance: Tolerances
    timed: bool
    origin_ns: int = 0          # log time of the window's first recorded message: report times count from it
    pilot: Any = None           # u2sa_hw.recording.pilot_check.PilotCheck of the recording (None: not checked)

    @property
    def ok(self) -> bool:
        """True when no stream differs and no recorded pilot message fails its signature check."""
        return all(s.ok for s in self.streams) and (self.pilot is None or self.pilot.ok)

    def summary(self) -> str:
        """One line for a CI log: ``compare: OK 6 streams ...`` or what differs, stream by stream; a recorded
        pilot message that fails its signature check comes first."""
        line = self._streams_summary()
        if self.pilot is None or self.pilot.ok:
            return line
        return f"compare: DIFFERENT: {self.pilot.short()}; streams: {line.removeprefix('compare: ')}"

    def seconds(self, t_ns: int | None) -> float | None:
        """*t_ns* as seconds into the compared window."""
        return None if t_ns is None else (t_ns - self.origin_ns) / 1e9

    def _streams_summary(self) -> str:
        bad = [s for s in self.streams if not s.ok]
        totals = (sum(s.matched for s in self.streams), sum(s.differing for s in self.streams),
                  sum(s.inserted for s in self.streams), sum(s.deleted for s in self.streams))
        counts = f"{totals[0]} matched, {totals[1]} different, {totals[2]} inserted, {totals[3]} deleted"
        if not self.streams:
            return "compare: NOTHING TO COMPARE (the replayed services published nothing)"
        if not bad:
            return f"compare: OK {len(self.streams)} streams; {counts}"
        what = "; ".join(f"{s.key} {_stream_counts(s)}" for s in bad[:4]) + ("; ..." if len(bad) > 4 else "")
        return f"compare: DIFFERENT {len(bad)} of {len(self.streams)} streams ({what}); {counts}"

    def format(self) -> str:
        """The printed report: a table, then each stream's problems, first differences and notes, then the summary."""
        lines = [f"compare: recorded {self.recorded} vs replayed {self.replayed} (tolerance {self.tolerance.default:g}"
                 f"{', per field from a file' if self.tolerance.fields else ''}; header timestamp and sequence not "
                 f"compared{'' if self.timed else '; timing not checked (--fast)'}; times are s into the recording)",
                 f"{'STREAM':32} {'RECORDED':>8} {'REPLAYED':>8} {'MATCHED':>7} {'DIFFER':>6} {'INS':>4} {'DEL':>4} "
                 f"{'TIME p50/max s':>15}  RESULT"]
        for s in self.streams:
            timing = "-" if s.time_max_s is None else f"{s.time_p50_s:.3f}/{s.time_max_s:.3f}"
            result = "DIFFERENT" if not s.ok else "same" if s.recorded else "new"
            lines.append(f"{s.key:32} {s.recorded:>8} {s.replayed:>8} {s.matched:>7} {s.differing:>6} "
                         f"{s.inserted:>4} {s.deleted:>4} {timing:>15}  {result}")
        for s in self.streams:
            for problem in s.problems:
                lines.append(f"  {s.key}: {problem}")
            for e in s.events[:SHOWN_EVENTS]:
                where = (f"recorded #{e.index} at t={self.seconds(e.t_ns):.3f} s is missing from the replay"
                         if e.kind == "deleted" else
                         f"replayed #{e.index} has no recorded counterpart (after t={self.seconds(e.t_ns):.3f} s)")
                lines.append(f"    {e.kind}: {where}")
            if len(s.events) > SHOWN_EVENTS:
                lines.append(f"    ... and {len(s.events) - SHOWN_EVENTS} more insertions/deletions")
            for d in sorted(s.fields.values(), key=lambda d: -d.count)[:SHOWN_FIELDS]:
                k, va, vb = d.first or (0, None, None)
                size = f", max |d| {d.max_abs:.6g}" if d.max_abs else ""
                at = "" if d.first_t_ns is None else f" t={self.seconds(d.first_t_ns):.3f} s"
                lines.append(f"    {d.name}: differs in {d.count} messages{size}; first at recorded #{k}{at}: "
                             f"recorded {va!r}, replayed {vb!r}")
            if len(s.fields) > SHOWN_FIELDS:
                lines.append(f"    ... and {len(s.fields) - SHOWN_FIELDS} more fields")
            for note in s.notes:
                lines.append(f"  {s.key}: note: {note}")
        if self.pilot is not None:
            lines.append(self.pilot.line())
        lines.append(self.summary())
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        """The report for tools (``--json``)."""
        return {
            "recorded": str(self.recorded), "replayed": str(self.replayed), "ok": self.ok, "timed": self.timed,
            "tolerance": {"default": self.tolerance.default, "fields": self.tolerance.fields,
                          "ignore": list(self.tolerance.ignore)},
            "summary": self.summary(),
            "pilot": None if self.pilot is None else self.pilot.to_dict(),
            "streams": [{
                "stream": s.key, "ok": s.ok, "recorded": s.recorded, "replayed": s.replayed, "matched": s.matched,
                "different": s.differing, "inserted": s.inserted, "deleted": s.deleted,
                "time_p50_s": s.time_p50_s, "time_max_s": s.time_max_s,
                "events": [{"kind": e.kind, "index": e.index, "t_s": self.seconds(e.t_ns)} for e in s.events],
                "fields": [{"field": d.name, "count": d.count, "max_abs": d.max_abs,
                            "first": None if d.first is None else {
                                "recorded_index": d.first[0], "t_s": self.seconds(d.first_t_ns),
                                "recorded": _json_value(d.first[1]), "replayed": _json_value(d.first[2])}}
                           for d in sorted(s.fields.values(), key=lambda d: -d.count)],
                "problems": s.problems, "notes": s.notes,
            } for s in self.streams],
        }


def _stream_counts(s: StreamReport) -> str:
    parts = [f"{n} {what}" for n, what in ((s.differing, "different"), (s.inserted, "inserted"),
                                           (s.deleted, "deleted")) if n]
    if not parts and s.problems:
        parts = [s.problems[0]]
    return ", ".join(parts) or "differs"
