"""The geofence on a matplotlib map (east right, north up, metres about the origin), as ``u2sa sim``'s track
plot and ``u2sa log plot`` draw it: inclusion areas as a green dashed outline, exclusion areas filled and
hatched red, each labelled with its name. matplotlib is imported by the callers (the ``sim`` extra).
"""

from __future__ import annotations

from typing import Any

from u2sa_hw.geofence import CIRCLE, Fence

INCLUSION_COLOUR = "#1e8449"
EXCLUSION_COLOUR = "#922b21"


def draw_fence(ax: Any, fence: Fence | None, patches: Any) -> int:
    """Add *fence*'s areas to the axes *ax* (*patches*: matplotlib.patches); returns how many were drawn."""
    if fence is None:
        return 0
    for n, area in enumerate(fence.areas):
        colour = INCLUSION_COLOUR if area.inclusion else EXCLUSION_COLOUR
        style: dict[str, Any] = {"edgecolor": colour, "linewidth": 1.8}
        if area.inclusion:
            style.update(fill=False, linestyle="--")
        else:
            style.update(facecolor=colour, alpha=0.25, hatch="//")
        if area.kind == CIRCLE:
            shape = patches.Circle((area.center[1], area.center[0]), area.radius_m, **style)
            label_at = (area.center[1], area.center[0] + area.radius_m)
        else:
            corners = [(east, north) for north, east in area.points]
            shape = patches.Polygon(corners, closed=True, **style)
            label_at = max(corners, key=lambda p: (p[1], -p[0]))   # the northernmost corner
        ax.add_patch(shape)
        ax.annotate(area.name, label_at, textcoords="offset points", xytext=(3, 3), fontsize=8, color=colour)
    if fence.inclusions:
        ax.plot([], [], "--", color=INCLUSION_COLOUR, label="geofence: stay inside")
    if fence.exclusions:
        ax.plot([], [], "s", color=EXCLUSION_COLOUR, alpha=0.4, label="geofence: stay out")
    return len(fence.areas)
