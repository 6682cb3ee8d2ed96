"""The summary of a simulated mission: time, distance, arrivals, cross-track, clearances.

Figures come from the simulated vehicle's *true* track (sampled in the ``u2sa sim``
process, which owns the SimVehicle), the mission status timeline heard on the bus, the
mission file's goals and the a-priori objects. Times are seconds from the moment the
vehicle went autonomous (the pilot's switch and the RC mux's enable line both said so).

Cross-track error is the distance from the true position to the straight leg the
vehicle is on: from the goal reached last (for the first goal: where the vehicle was
when it went autonomous) to the current goal. Steering around an obstacle shows up
in it, by design.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Iterable, Sequence

from u2sa_hw.simulation.fence_report import fence_lines, fence_report
from u2sa_hw.simulation.progress import StatusChange
from u2sa_hw.services.world.shapes import distance_to_point, segment_distance


@dataclass(frozen=True)
class Goal:
    """A mission goal as drawn and measured: uid, local NED position (m), completion radius (m)."""

    uid: str
    north: float
    east: float
    threshold: float


@dataclass(frozen=True)
class TrackSample:
    """One sample of the run: true pose and speed, the estimate then, the current goal index."""

    t: float
    north: float
    east: float
    yaw: float
    speed: float
    est_north: float | None = None
    est_east: float | None = None
    goal_index: int | None = None


@dataclass
class RunRecord:
    """Everything the summary is computed from (times: time.monotonic())."""

    vehicle: str
    mission: str
    looping: bool
    goals: list[Goal]
    obstacles: list[Any]
    samples: list[TrackSample] = field(default_factory=list)
    changes: list[StatusChange] = field(default_factory=list)
    t_start: float = 0.0
    t_engage: float | None = None
    t_end: float = 0.0
    result: str = "failed"
    reason: str = ""
    services: dict[str, dict[str, Any]] = field(default_factory=dict)
    interruptions: list[dict[str, Any]] = field(default_factory=list)
    fence: Any = None                    # u2sa_hw.geofence.Fence of the profile, or None


def _rel(t: float | None, t0: float | None) -> float | None:
    return None if t is None or t0 is None else round(t - t0, 2)


def arrivals(record: RunRecord) -> list[dict[str, Any]]:
    """Each goal reached, in order: uid, index, arrival time (s after engaging)."""
    out, previous = [], None
    for change in record.changes:
        if record.t_engage is not None and change.t < record.t_engage - 1.0:
            previous = change
            continue
        if previous is not None and not previous.finished and (change.uid, change.index) != (previous.uid,
                                                                                              previous.index):
            out.append({"uid": previous.uid, "index": previous.index, "arrival_s": _rel(change.t, record.t_engage)})
        previous = change
    return out


def _object_name(obj: Any) -> tuple[str, str]:
    from u2sa_hw import lcmtypes as t
    from u2sa_hw.messages import as_type

    base = as_type(obj, t.ObjectDescription)
    return base.uid, base.object_type


def track_sample(truth: Any, snap: Any, now: float) -> TrackSample:
    """One sample of the track at *now*: the simulated vehicle's true pose (*truth*) and, from the bus snapshot
    *snap*, the stack's estimate when at most 0.5 s old and the goal it drives to."""
    est = snap.estimate
    fresh = est is not None and now - est[0] < 0.5
    st = snap.status
    return TrackSample(t=now, north=truth.north, east=truth.east, yaw=truth.yaw, speed=truth.speed,
                       est_north=est[1] if fresh else None, est_east=est[2] if fresh else None,
                       goal_index=st.current_index if st is not None and not st.finished else None)


def run_title(r: RunRecord) -> str:
    """The run in one line, the plot's title: ``rover: mission 'loop' completed in 42.0 s``."""
    took = f" in {r.t_end - r.t_engage:.1f} s" if r.t_engage is not None else ""
    return f"{r.vehicle}: mission '{r.mission}' {r.result}{took}"


def summarise(record: RunRecord) -> dict[str, Any]:
    """The summary as a JSON-ready dict."""
    live = [s for s in record.samples if record.t_engage is not None and s.t >= record.t_engage]
    # Distance and speeds from the whole simulated track (track.csv): a scenario the pilot drives by hand
    # never goes autonomous, and what he drove is still driven.
    track = record.samples
    distance = sum(math.hypot(b.north - a.north, b.east - a.east) for a, b in zip(track, track[1:]))
    mission_time = _rel(record.t_end, record.t_engage)
    track_time = track[-1].t - track[0].t if len(track) > 1 else None
    worst, worst_leg, leg_from, last_index = 0.0, "", None, None
    for s in live:
        if s.goal_index is None or not 0 <= s.goal_index < len(record.goals):
            continue
        if leg_from is None:
            leg_from = (s.north, s.east, "start")
        elif s.goal_index != last_index and last_index is not None:
            g = record.goals[last_index]
            leg_from = (g.north, g.east, g.uid)
        last_index = s.goal_index
        goal = record.goals[s.goal_index]
        error = segment_distance(s.north, s.east, leg_from[0], leg_from[1], goal.north, goal.east)
        if error > worst:
            worst, worst_leg = error, f"{leg_from[2]} -> {goal.uid}"
    clearances = []
    for obj in record.obstacles:
        uid, kind = _object_name(obj)
        closest = min((distance_to_point(obj, s.north, s.east) for s in live), default=None)
        clearances.append({"uid": uid, "type": kind,
                           "min_clearance_m": None if closest is None else round(closest, 2)})
    errors = sorted(math.hypot(s.est_north - s.north, s.est_east - s.east) for s in live
                    if s.est_north is not None and s.est_east is not None)
    speeds = [s.speed for s in track]
    reached = arrivals(record)
    return {
        "result": record.result,
        "reason": record.reason,
        "vehicle": record.vehicle,
        "mission": record.mission,
        "looping": record.looping,
        "startup_s": _rel(record.t_engage, record.t_start),
        "mission_time_s": mission_time,
        "wall_time_s": round(record.t_end - record.t_start, 2),
        "distance_m": round(distance, 2),
        "mean_speed_mps": round(distance / span, 2) if (span := mission_time or track_time) else None,
        "max_speed_mps": round(max(speeds), 2) if speeds else None,
        "goals": [{"uid": g.uid, "north": g.north, "east": g.east, "threshold_m": g.threshold,
                   "arrival_s": next((a["arrival_s"] for a in reached if a["uid"] == g.uid), None)}
                  for g in record.goals],
        "arrivals": reached,
        "max_cross_track_m": round(worst, 2),
        "max_cross_track_leg": worst_leg,
        "obstacles": clearances,
        "estimate_error_m": {"mean": round(sum(errors) / len(errors), 3) if errors else None,
                             "p95": round(errors[int(0.95 * (len(errors) - 1))], 3) if errors else None,
                             "max": round(errors[-1], 3) if errors else None},
        "autonomy_interruptions": record.interruptions,
        "geofence": fence_report(record.fence, record.samples, t_engage=record.t_engage),
        "services": record.services,
    }


def _fmt(value: float | None, unit: str, digits: int = 1) -> str:
    return "--" if value is None else f"{value:.{digits}f} {unit}"


def _event_outcome(event: dict[str, Any]) -> str:
    """``all neutral after 97 ms; moved again: left_wheel, right_wheel; RC_MODE NO RC SIGNAL``."""
    moving = [n for n, o in event["outputs"].items() if not o["at_event"]["neutral"]]
    after = event["all_neutral_after_ms"]
    parts = ["nothing was moving" if not moving else
             f"all neutral after {after:.0f} ms" if after is not None
             else "kept moving (not all neutral in the window)"]
    moved = [n for n, o in event["outputs"].items() if o["moved_after_ms"] is not None]
    if moved:
        parts.append("moved: " + ", ".join(moved))
    if event["rc_modes"]:
        parts.append("RC_MODE " + " -> ".join(event["rc_modes"]))
    if event.get("rc_receiver_stalled_ms"):
        parts.append(f"the simulated RC receiver stalled {event['rc_receiver_stalled_ms']:.0f} ms (machine overloaded)")
    return "; ".join(parts)


def summary_text(summary: dict[str, Any], *, files: Iterable[Path] = ()) -> str:
    """A short human summary (what u2sa sim prints at the end and writes to summary.txt)."""
    times = (f"(startup {_fmt(summary['startup_s'], 's')}, wall {_fmt(summary['wall_time_s'], 's')})")
    if summary["result"] == "played":   # a scenario ran to its end: "completed" is said only of reached goals
        scenario = summary.get("scenario", {}).get("name", "")
        engaged = (f"{_fmt(summary['mission_time_s'], 's')} after engaging" if summary["mission_time_s"] is not None
                   else "never autonomous")
        first = (f"not completed ({len(summary['arrivals'])} of {len(summary['goals'])} goals reached); scenario "
                 + (f"'{scenario}' " if scenario else "") + f"played to its end, {engaged} {times}")
    else:
        head = {"completed": "completed", "timeout": "TIMED OUT", "failed": "FAILED"}.get(summary["result"],
                                                                                         summary["result"])
        first = f"{head} in {_fmt(summary['mission_time_s'], 's')} {times}"
    lines = [f"mission '{summary['mission']}' on {summary['vehicle']}: {first}"]
    if summary["reason"]:
        lines.append(f"  reason               {summary['reason']}")
    lines.append(f"  distance driven      {_fmt(summary['distance_m'], 'm')}, mean speed "
                 f"{_fmt(summary['mean_speed_mps'], 'm/s', 2)}, top {_fmt(summary['max_speed_mps'], 'm/s', 2)}")
    goals = ", ".join(f"{a['uid']} {_fmt(a['arrival_s'], 's')}" for a in summary["arrivals"]) or "none reached"
    lines.append(f"  goals reached        {goals}")
    lines.append(f"  largest cross-track  {_fmt(summary['max_cross_track_m'], 'm', 2)}"
                 + (f" ({summary['max_cross_track_leg']})" if summary["max_cross_track_leg"] else ""))
    if summary["obstacles"]:
        lines.append("  closest approach     " + ", ".join(
            f"{o['uid']} {_fmt(o['min_clearance_m'], 'm', 2)}" for o in summary["obstacles"]))
    err = summary["estimate_error_m"]
    lines.append(f"  estimate vs truth    mean {_fmt(err['mean'], 'm', 2)}, p95 {_fmt(err['p95'], 'm', 2)}, "
                 f"max {_fmt(err['max'], 'm', 2)}")
    lines += fence_lines(summary.get("geofence"))
    for gap in summary["autonomy_interruptions"]:
        lines.append(f"  autonomy lost        at {gap['at_s']:.1f} s ({gap['why']}), re-engaged by the pilot")
    restarts = {n: s.get("restarts", 0) for n, s in summary["services"].items() if s.get("restarts")}
    lines.append(f"  services             {len(summary['services'])} run, "
                 + (", ".join(f"{n} restarted {k}x" for n, k in restarts.items()) if restarts else "no restarts"))
    for event in summary.get("scenario", {}).get("events", []):
        lines.append(f"  {event['fired_s']:6.1f} s {event['event']}: {_event_outcome(event)}")
    for path in files:
        lines.append(f"  wrote                {path}")
    return "\n".join(lines)


def write_summary(summary: dict[str, Any], out: Path, *, extra_files: Sequence[Path] = ()) -> tuple[Path, Path]:
    """Write ``summary.json`` and ``summary.txt`` into *out*; returns their paths."""
    out.mkdir(parents=True, exist_ok=True)
    json_path, text_path = out / "summary.json", out / "summary.txt"
    json_path.write_text(json.dumps(summary, indent=2) + "\n")
    text_path.write_text(summary_text(summary, files=[json_path, *extra_files]) + "\n")
    return json_path, text_path


def write_track_csv(samples: Sequence[TrackSample], path: Path) -> Path:
    """The sampled track as CSV (t in s from the first sample; true and estimated position; goal index)."""
    names = [f.name for f in fields(TrackSample)]
    t0 = samples[0].t if samples else 0.0
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(names)
        for row in samples:
            values = asdict(row)
            values["t"] = round(row.t - t0, 3)
            writer.writerow(["" if values[n] is None else values[n] for n in names])
    return path
