"""The geofence in a simulation's summary: where the TRUE track went against the profile's fence.

``geofence`` in summary.json: the areas, every breach (when the true position left the allowed
area, in seconds after autonomy engaged, which area, how far out it got before it came back or
the run ended, and ``estimate_out_s``: when the estimate was first outside too, which is what the
vehicle acts on; samples at the track's rate) and the closest the track came to a line while inside. The vehicle's own reaction
(pre-arm refusal, the lost check's neutral or hold) is in ``autonomy_interruptions`` and in the
scenario's events, as for every other check.
"""

from __future__ import annotations

from typing import Any, Sequence


def fence_report(fence: Any, samples: Sequence[Any], *, t_engage: float | None) -> dict[str, Any] | None:
    """The summary's ``geofence`` section for *fence* (None without one) over the true track *samples*."""
    if fence is None:
        return None
    base = t_engage if t_engage is not None else (samples[0].t if samples else 0.0)
    breaches: list[dict[str, Any]] = []
    closest: float | None = None
    current: dict[str, Any] | None = None
    for s in samples:
        hit = fence.breach(s.north, s.east)
        if hit is None:
            current = None
            gap = fence.clearance(s.north, s.east)
            closest = gap if closest is None else min(closest, gap)
            continue
        depth = hit.area.edge_distance(s.north, s.east)
        if current is None or current["area"] != hit.area.name:
            current = {"at_s": round(s.t - base, 2), "area": hit.area.name, "what": hit.what, "max_out_m": 0.0,
                       "estimate_out_s": None}
            breaches.append(current)
        if current["estimate_out_s"] is None and s.est_north is not None and s.est_east is not None \
                and fence.breach(s.est_north, s.est_east) is not None:
            current["estimate_out_s"] = round(s.t - base, 2)
        current["max_out_m"] = round(max(current["max_out_m"], depth), 2)
    return {"areas": [a.name for a in fence.areas], "breaches": breaches,
            "closest_to_a_line_m": None if closest is None else round(closest, 2)}


def fence_lines(report: dict[str, Any] | None) -> list[str]:
    """The summary text's lines for the ``geofence`` section."""
    if report is None:
        return []
    if not report["breaches"]:
        closest = report["closest_to_a_line_m"]
        return [f"  geofence             kept inside ({', '.join(report['areas'])})"
                + (f", closest {closest:.2f} m from a line" if closest is not None else "")]
    return [f"  geofence             BREACHED at {b['at_s']:.1f} s: {b['what']} (up to {b['max_out_m']:.1f} m)"
            for b in report["breaches"]]
