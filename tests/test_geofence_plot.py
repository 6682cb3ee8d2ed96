"""The geofence on the maps: the recorder attaches it to a log (run_info), ``u2sa log plot`` and the simulation's
track plot draw it (artists checked, not pixels)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import tomli_w

pytest.importorskip("matplotlib")

from matplotlib import patches  # noqa: E402

from u2sa_hw import lcmtypes as t  # noqa: E402
from u2sa_hw.geofence import Fence  # noqa: E402
from u2sa_hw.messages import STATE_FIELDS  # noqa: E402,F401 - installs the presence setters
from u2sa_hw.recording.mcap_log import McapLogWriter  # noqa: E402
from u2sa_hw.recording.plot import log_figure, plot_log  # noqa: E402
from u2sa_hw.services.recorder.service import run_info  # noqa: E402
from u2sa_hw.profile.loader import load_profile  # noqa: E402

FENCE = {"polygons": [{"name": "field", "local": [[-5, -5], [30, -5], [30, 20], [-5, 20]]}],
         "circles": [{"name": "pond", "inclusion": False, "local_center": [10, 8], "radius_m": 3}]}


def fenced_profile(tmp_path: Path) -> Path:
    path = tmp_path / "vehicle.toml"
    path.write_text(tomli_w.dumps({"vehicle": {"name": "rover", "origin": {"lat": 29.19, "lon": -81.05, "alt": 10.0}},
                                   "services": {"estimator": {"kind": "state_estimator"}}, "geofence": FENCE}))
    return path


def fence_artists(ax: object) -> tuple[list[patches.Polygon], list[patches.Circle]]:
    polygons = [p for p in ax.patches if isinstance(p, patches.Polygon)]
    circles = [p for p in ax.patches if isinstance(p, patches.Circle)]
    return polygons, circles


def test_the_log_carries_the_fence_and_log_plot_draws_it(tmp_path: Path) -> None:
    info = run_info(load_profile(fenced_profile(tmp_path)), "udpm://239.255.76.67:7667?ttl=0")
    fence = Fence.from_json(info.attachments["geofence.json"])
    assert [a.name for a in fence.areas] == ["field", "pond"]
    path = tmp_path / "run.mcap"
    writer = McapLogWriter(tmp_path, path=path, run=info)
    t0 = time.time_ns()
    for i in range(5):
        s = t.StateInformation().set(x=float(i), y=0.0, psi=0.0)
        s.sensor_name = "state_estimator"
        writer.write("STATE_ESTIMATE", s.encode(), t0 + i * 100_000_000)
    writer.close()

    fig, run = log_figure(path)
    assert run.fence is not None and run.fence.areas == fence.areas
    polygons, circles = fence_artists(fig.axes[0])
    (field,) = polygons
    assert [tuple(v) for v in field.get_xy()[:4]] == [(-5, -5), (-5, 30), (20, 30), (20, -5)]   # (east, north)
    (pond,) = circles
    assert pond.center == pytest.approx((8.0, 10.0)) and pond.get_radius() == 3.0
    labels = fig.axes[0].get_legend_handles_labels()[1]
    assert "geofence: stay inside" in labels and "geofence: stay out" in labels
    assert plot_log(path, tmp_path / "run.png")["fence_areas"] == 2


def test_a_log_without_a_fence_draws_none(tmp_path: Path) -> None:
    profile = tmp_path / "plain.toml"
    profile.write_text('[vehicle]\nname = "rover"\n')
    info = run_info(load_profile(profile), "udpm://239.255.76.67:7667?ttl=0")
    assert "geofence.json" not in info.attachments
    path = tmp_path / "plain.mcap"
    writer = McapLogWriter(tmp_path, path=path, run=info)
    writer.write("STATE_ESTIMATE", t.StateInformation().set(x=0.0, y=0.0, psi=0.0).encode(), time.time_ns())
    writer.close()
    fig, run = log_figure(path)
    assert run.fence is None and fence_artists(fig.axes[0]) == ([], [])
