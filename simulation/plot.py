"""The PNG of a simulated mission: the driven track (coloured by speed), the estimate, the
waypoints with their completion circles, the legs between them, the a-priori obstacles and the
geofence.

A map view: east to the right, north up, metres about the profile's origin. matplotlib
is imported here only (the ``sim`` extra), with the Agg backend, so no display is needed.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Sequence

from u2sa_hw.simulation.summary import Goal, TrackSample
from u2sa_hw import lcmtypes as t
from u2sa_hw.messages import as_type
from u2sa_hw.geofence_draw import draw_fence
from u2sa_hw.recording.plot import obstacle_patch

def plot_run(path: Path, *, samples: Sequence[TrackSample], goals: Sequence[Goal], obstacles: Sequence[Any],
             title: str, t_engage: float | None = None, fence: Any = None) -> Path:
    """Draw the run into *path* (PNG); returns *path*."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import patches
    from matplotlib.collections import LineCollection

    live = [s for s in samples if t_engage is None or s.t >= t_engage] or list(samples)
    fig, ax = plt.subplots(figsize=(8.5, 7.5), dpi=110)
    draw_fence(ax, fence, patches)
    for obj in obstacles:
        ax.add_patch(obstacle_patch(obj, patches))
        base = as_type(obj, t.ObjectDescription)
        ax.annotate(base.uid, (base.y, base.x), ha="center", va="center", fontsize=8, color="#7b241c")
    if live:
        start = (live[0].east, live[0].north)
        legs = [start] + [(g.east, g.north) for g in goals]
        ax.plot([p[0] for p in legs], [p[1] for p in legs], ":", color="0.55", linewidth=1, label="planned legs")
        est = [(s.est_east, s.est_north) for s in live if s.est_east is not None]
        if est:
            ax.plot([p[0] for p in est], [p[1] for p in est], "--", color="0.35", linewidth=0.8,
                    label="estimated position")
        points = [(s.east, s.north) for s in live]
        segments = [[a, b] for a, b in zip(points, points[1:])]
        lines = LineCollection(segments, cmap="viridis", linewidths=2.5)
        lines.set_array([s.speed for s in live[1:]])
        ax.add_collection(lines)
        fig.colorbar(lines, ax=ax, label="true speed (m/s)", shrink=0.8)
        heading = live[0].yaw
        ax.annotate("", xy=(start[0] + 2.0 * math.sin(heading), start[1] + 2.0 * math.cos(heading)), xytext=start,
                    arrowprops={"arrowstyle": "->", "color": "black", "linewidth": 1.5})
        ax.plot(*start, "ko", markersize=6, label="start")
        ax.plot(live[-1].east, live[-1].north, "ks", markersize=6, label="end")
    for number, goal in enumerate(goals, start=1):
        ax.add_patch(patches.Circle((goal.east, goal.north), goal.threshold, fill=False, edgecolor="#1f618d",
                                    linestyle="--", linewidth=1))
        ax.plot(goal.east, goal.north, "x", color="#1f618d", markersize=9, markeredgewidth=2)
        ax.annotate(f"{number} {goal.uid}", (goal.east, goal.north), textcoords="offset points", xytext=(6, 6),
                    fontsize=9, color="#1f618d")
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.margins(0.08)
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(title, fontsize=11)
    ax.grid(True, linewidth=0.4, alpha=0.6)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
