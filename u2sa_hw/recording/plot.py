"""``u2sa log plot``: a log's run on one page.

Left, the map view (east right, north up, metres about the origin) as the simulation
draws it: the track, the waypoints with their threshold circles, the obstacles of
``WORLD`` (their last known shape) and the geofence (the log's ``geofence.json``, which the
recorder attaches from the profile). Right, over time: the heading (unwrapped, so a turn
through north is a slope, not a jump of 360 degrees), the speed, every actuator's
commands (``ACTUATOR_CMD`` solid, the pilot's ``MANUAL_CMD`` dashed) and a panel with the
RC mode (autonomy shaded) and the failsafes. Legends sit beside their panels, never on
the track. The title names the vehicle, the mission and the file.

The failsafes are rebuilt as every holder keeps them (:class:`u2sa_hw.failsafe.FailsafeSources`):
per source, a source clears only its own and the operator clears one by name or all with
``*``; a red span lasts while any source holds one. Objects and waypoints in geodetic
coordinates are placed about the log's origin (the ``vehicle.toml`` it carries), as the
export places them; without an origin they are left out.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.channels import base_type
from u2sa_hw.failsafe import FailsafeSources
from u2sa_hw.geo import geodetic_to_ned
from u2sa_hw.geofence_draw import draw_fence
from u2sa_hw.messages import REGISTRY, MalformedMessage, as_type
from u2sa_hw.recording.log_reader import LogFile
from u2sa_hw.services.world.model import GEODETIC_FRAMES, NED_FRAMES, PlacementError, place_in_world

WAYPOINT_COLOUR = "#1f618d"
FAILSAFE_COLOUR = "#c0392b"
AUTONOMY_COLOUR = "#27ae60"


OBSTACLE_COLOUR = "#c0392b"


def obstacle_patch(obj: Any, patches: Any) -> Any:
    """A matplotlib patch for an object in NED, drawn in (east, north) axes (*patches*: matplotlib.patches);
    the simulation's track plot draws its obstacles with it too."""
    base = as_type(obj, t.ObjectDescription)
    style = {"facecolor": OBSTACLE_COLOUR, "edgecolor": OBSTACLE_COLOUR, "alpha": 0.35, "linewidth": 1.5}
    if isinstance(obj, (t.Circle, t.Sphere)):
        radius = obj.radius if isinstance(obj, t.Circle) else obj.sphere_radius
        return patches.Circle((base.y, base.x), max(radius, 0.3), **style)   # radius 0: a point, drawn as a dot
    if isinstance(obj, t.Rectangle):
        c, s = math.cos(obj.heading), math.sin(obj.heading)
        corners = []
        for along, across in ((1, 1), (1, -1), (-1, -1), (-1, 1)):
            a, b = along * obj.length / 2, across * obj.width / 2
            corners.append((base.y + a * s + b * c, base.x + a * c - b * s))
        return patches.Polygon(corners, closed=True, **style)
    if isinstance(obj, t.Polygon):
        return patches.Polygon(list(zip(obj.vy, obj.vx)), closed=True, **style)
    return patches.Circle((base.y, base.x), 0.3, **style)



@dataclass
class RunData:
    """What the plot needs from a log (times in s from the first message)."""

    vehicle: str = ""
    mission: str = ""
    track: list[tuple[float, float, float]] = field(default_factory=list)     # t, north, east
    heading: list[tuple[float, float]] = field(default_factory=list)          # t, rad (wrapped)
    speed: list[tuple[float, float]] = field(default_factory=list)
    commands: dict[tuple[str, str], list[tuple[float, float]]] = field(default_factory=lambda: defaultdict(list))
    waypoints: dict[str, Any] = field(default_factory=dict)                   # uid -> last Waypoint
    obstacles: dict[str, Any] = field(default_factory=dict)                   # uid -> last WORLD object
    rc_modes: list[tuple[float, str, bool]] = field(default_factory=list)     # t, mode name, autonomy enabled
    failsafes: list[tuple[float, dict[str, str]]] = field(default_factory=list)  # t, source -> reason held after
    fence: Any = None                                                         # u2sa_hw.geofence.Fence
    end: float = 0.0


def read_run(src: Path | str, *, channel: str = ch.STATE_ESTIMATE) -> RunData:
    """Collect the plotted series from log *src*."""
    from u2sa_hw.recording.foxglove import log_origin

    log = LogFile(src)
    run = RunData()
    held = FailsafeSources()
    t0: int | None = None
    origin = None
    wanted = {channel, ch.ACTUATOR_CMD, ch.MANUAL_CMD, ch.GOALS, ch.WORLD, ch.RC_MODE, ch.FAILSAFE, ch.MISSION_STATUS}
    for m in log.messages():
        if t0 is None:
            t0, origin = m.log_time_ns, log_origin(log)[0]
            run.vehicle = log.contents.metadata.get("u2sa", {}).get("vehicle", "")
            run.fence = _fence(log)
        tm = (m.log_time_ns - t0) / 1e9
        run.end = max(run.end, tm)
        if m.channel not in wanted:
            continue
        try:
            msg, _ = REGISTRY.decode(m.data, base_type(m.channel))
        except MalformedMessage:
            continue
        if m.channel == channel and isinstance(msg, t.StateInformation):
            _state(run, msg, tm)
        elif m.channel in (ch.ACTUATOR_CMD, ch.MANUAL_CMD) and hasattr(msg, "percentage"):
            run.commands[(msg.base.actuator_name, m.channel)].append((tm, msg.percentage))
        elif m.channel == ch.GOALS and isinstance(msg, t.Waypoint):
            geodetic = msg.reference_frame.strip().upper() in GEODETIC_FRAMES
            if geodetic and origin is not None:
                msg.x, msg.y, _ = geodetic_to_ned(msg.x, msg.y, None, origin=origin)
                msg.reference_frame, geodetic = "LOCAL", False
            if not geodetic:
                run.waypoints[msg.base.uid] = msg
        elif m.channel == ch.WORLD:
            try:
                base = as_type(msg, t.ObjectDescription)
            except TypeError:
                continue
            placed = _placed(msg, base, origin)
            if placed is not None:
                run.obstacles[base.uid] = placed
        elif m.channel == ch.RC_MODE and isinstance(msg, t.RcMode):
            if not run.rc_modes or run.rc_modes[-1][1:] != (msg.mode_name, msg.autonomy_enabled):
                run.rc_modes.append((tm, msg.mode_name or str(msg.mode), msg.autonomy_enabled))
        elif m.channel == ch.FAILSAFE and isinstance(msg, t.Failsafe):
            change = held.apply_message(msg)
            if change.raised or change.cleared:   # a repeat of a held failsafe changes nothing
                run.failsafes.append((tm, held.held()))
        elif m.channel == ch.MISSION_STATUS and isinstance(msg, t.MissionStatus) and msg.mission_name:
            run.mission = msg.mission_name
    return run


def _fence(log: LogFile) -> Any:
    """The geofence the log carries, or None (none recorded, or unreadable: the map is drawn without it)."""
    from u2sa_hw.geofence import Fence

    data = log.contents.attachments.get("geofence.json")
    try:
        return Fence.from_json(data) if data else None
    except (ValueError, KeyError, TypeError, IndexError):
        return None


def _placed(msg: Any, base: Any, origin: Any) -> Any:
    """*msg* (a WORLD object) in local NED, or None: geodetic ones need *origin*, body-frame ones a pose."""
    frame = base.reference_frame.strip().upper()
    if frame in NED_FRAMES:
        return msg
    if origin is None:
        return None
    try:
        return place_in_world(msg, pose=None, origin=origin)
    except PlacementError:   # FRD: relative to a pose the log's world modeler had; its own output is NED
        return None


def failsafe_spans(run: RunData) -> list[tuple[float, float, str]]:
    """(start, end, who held it) of every stretch in which any source held a failsafe."""
    spans: list[tuple[float, float, str]] = []
    start: float | None = None
    holders: dict[str, str] = {}
    for tm, held in run.failsafes:
        if held and start is None:
            start, holders = tm, {}
        for src, why in held.items():
            holders.setdefault(src, why)
        if not held and start is not None:
            spans.append((start, tm, _holders_text(holders)))
            start = None
    if start is not None:
        spans.append((start, run.end, _holders_text(holders)))
    return spans


def _holders_text(holders: dict[str, str]) -> str:
    return "; ".join(f"{src}: {why or 'no reason given'}" for src, why in holders.items())


def _state(run: RunData, msg: Any, tm: float) -> None:
    if msg.reference_frame not in ("NED", ""):
        return
    if msg.has("x") and msg.has("y") and math.isfinite(msg.x) and math.isfinite(msg.y):
        run.track.append((tm, msg.x, msg.y))
    if msg.has("psi") and math.isfinite(msg.psi):
        run.heading.append((tm, msg.psi))
    if msg.has("x_dot") and msg.has("y_dot"):
        run.speed.append((tm, math.hypot(msg.x_dot, msg.y_dot)))


def unwrapped_degrees(angles: list[float]) -> list[float]:
    """Headings in degrees without the jumps at +-180: each step is the shortest turn."""
    out: list[float] = []
    for a in angles:
        d = math.degrees(a)
        if out:
            d = out[-1] + ((d - out[-1] + 180.0) % 360.0 - 180.0)
        out.append(d)
    return out


def build_figure(run: RunData, *, title: str, channel: str = ch.STATE_ESTIMATE) -> Any:
    """The matplotlib Figure of *run* (Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import patches


    fig = plt.figure(figsize=(15, 10), dpi=100)
    grid = fig.add_gridspec(4, 2, width_ratios=(1.15, 1.0), hspace=0.45, wspace=0.28)
    ax = fig.add_subplot(grid[:, 0])
    draw_fence(ax, run.fence, patches)
    for obj in run.obstacles.values():
        ax.add_patch(obstacle_patch(obj, patches))
        base = as_type(obj, t.ObjectDescription)
        ax.annotate(base.uid, (base.y, base.x), ha="center", va="center", fontsize=8, color="#7b241c")
    if run.obstacles:
        ax.plot([], [], "s", color="#c0392b", alpha=0.5, label="obstacles (WORLD)")
    for number, (uid, wp) in enumerate(run.waypoints.items(), start=1):
        if wp.horizontal_threshold > 0:
            ax.add_patch(patches.Circle((wp.y, wp.x), wp.horizontal_threshold, fill=False, edgecolor=WAYPOINT_COLOUR,
                                        linestyle="--", linewidth=1))
        ax.plot(wp.y, wp.x, "x", color=WAYPOINT_COLOUR if not wp.base.completed else "0.5", markersize=9,
                markeredgewidth=2, label="waypoints (threshold dashed)" if number == 1 else None)
        ax.annotate(f"{number} {uid}", (wp.y, wp.x), textcoords="offset points", xytext=(6, 6), fontsize=9,
                    color=WAYPOINT_COLOUR)
    if run.track:
        ax.plot([p[2] for p in run.track], [p[1] for p in run.track], "-", lw=1.8, color="#2e86c1",
                label=f"track ({channel})")
        ax.plot(run.track[0][2], run.track[0][1], "go", label="start")
        ax.plot(run.track[-1][2], run.track[-1][1], "ks", label="end")
    ax.set(title="map (m about the origin)", xlabel="east (m)", ylabel="north (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.margins(0.08)
    ax.grid(True, linewidth=0.4, alpha=0.6)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.07), ncol=3, fontsize=8, frameon=False)
    _series(fig.add_subplot(grid[0, 1]), [([p[0] for p in run.heading], unwrapped_degrees([p[1] for p in run.heading]),
                                           "estimate")], "heading (unwrapped)", "deg", run.end)
    _series(fig.add_subplot(grid[1, 1]), [([p[0] for p in run.speed], [p[1] for p in run.speed], "estimate")],
            "speed", "m/s", run.end)
    cmd = fig.add_subplot(grid[2, 1])
    _series(cmd, [([p[0] for p in s], [p[1] for p in s], f"{name} ({'manual' if chan == ch.MANUAL_CMD else 'auto'})")
                  for (name, chan), s in sorted(run.commands.items())], "actuator commands", "%", run.end,
            dashed={ch.MANUAL_CMD})
    cmd.set_ylim(-105, 105)
    _modes(fig.add_subplot(grid[3, 1]), run)
    fig.suptitle(title, fontsize=13)
    fig.subplots_adjust(left=0.05, right=0.86, top=0.93, bottom=0.1)
    return fig


def _series(ax: Any, lines: list[tuple[list[float], list[float], str]], title: str, unit: str, end: float, *,
            dashed: set[str] | None = None) -> None:
    for xs, ys, label in lines:
        style = "--" if dashed and "(manual)" in label else "-"
        ax.plot(xs, ys, style, lw=1.1, label=label)
    ax.set(title=title, ylabel=unit, xlim=(0, max(end, 1e-3)))
    ax.grid(True, linewidth=0.4, alpha=0.6)
    if len(lines) > 1:
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, frameon=False)


def _modes(ax: Any, run: RunData) -> None:
    """RC mode as steps (autonomy granted shaded green) and failsafes as red spans naming their holders."""
    names = sorted({m for _t, m, _a in run.rc_modes})
    level = {n: i for i, n in enumerate(names)}
    bounds = [tm for tm, _m, _a in run.rc_modes] + [run.end]
    for (tm, mode, auto), nxt in zip(run.rc_modes, bounds[1:]):
        ax.hlines(level[mode], tm, nxt, color="#34495e", lw=2)
        if auto:
            ax.axvspan(tm, nxt, color=AUTONOMY_COLOUR, alpha=0.15, lw=0)
    spans = failsafe_spans(run)
    for start, end, holders in spans:
        ax.axvspan(start, end, color=FAILSAFE_COLOUR, alpha=0.3, lw=0)
        ax.annotate(holders[:60], (start, max(len(names) - 0.6, 0.4)), fontsize=7, color=FAILSAFE_COLOUR)
    ax.set_yticks(range(len(names)), names)
    ax.set_ylim(-0.6, max(len(names) - 0.4, 0.6))
    ax.set(title="RC mode (autonomy granted: green) and failsafes (red)", xlabel="time (s)",
           xlim=(0, max(run.end, 1e-3)))
    ax.plot([], [], color=AUTONOMY_COLOUR, alpha=0.4, lw=8, label="autonomy granted")
    ax.plot([], [], color=FAILSAFE_COLOUR, alpha=0.5, lw=8, label=f"failsafe ({len(spans)})")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, frameon=False)
    ax.grid(True, axis="x", linewidth=0.4, alpha=0.6)


def plot_title(run: RunData, src: Path | str) -> str:
    """The page's title: the vehicle, the mission, the file and how long the log runs."""
    return (f"{run.vehicle or 'unknown vehicle'} -- mission {run.mission or '(none in the log)'} -- "
            f"{Path(src).name} ({run.end:.0f} s)")


def log_figure(src: Path | str, *, channel: str = ch.STATE_ESTIMATE) -> tuple[Any, RunData]:
    """The figure ``u2sa log plot`` saves for log *src*, and the run it draws."""
    run = read_run(src, channel=channel)
    return build_figure(run, title=plot_title(run, src), channel=channel), run


def plot_log(src: Path | str, out: Path | str, *, channel: str = ch.STATE_ESTIMATE) -> dict[str, int]:
    """Draw the run in log *src* into the PNG *out*; return how many items each part holds."""
    fig, run = log_figure(src, channel=channel)   # build_figure selects matplotlib's Agg backend first
    import matplotlib.pyplot as plt

    fig.savefig(out)
    plt.close(fig)
    return {"track": len(run.track), "heading": len(run.heading), "speed": len(run.speed),
            "commands": sum(len(s) for s in run.commands.values()), "waypoints": len(run.waypoints),
            "obstacles": len(run.obstacles), "fence_areas": len(run.fence.areas) if run.fence else 0,
            "rc_modes": len(run.rc_modes),
            "failsafes": len(failsafe_spans(run))}
