"""``u2sa log plot`` of a recorded simulation: the page holds the map with the waypoints, their thresholds
and the obstacles, the unwrapped heading, the commands and the RC mode panel; the legend is off the track
and the title names the vehicle and the mission (artists checked, not pixels)."""

from __future__ import annotations

import math
import subprocess
from pathlib import Path

import pytest
from conftest import REPO, U2SA
from recorded_sim import recorded_sim

pytest.importorskip("matplotlib")

from matplotlib import patches  # noqa: E402

from u2sa_hw.recording.plot import build_figure, read_run, unwrapped_degrees  # noqa: E402


def test_unwrapped_heading_turns_through_north_without_a_jump() -> None:
    assert unwrapped_degrees([math.radians(170), math.radians(-170), math.radians(-100)]) == pytest.approx(
        [170.0, 190.0, 260.0])
    assert unwrapped_degrees([math.radians(-175), math.radians(175)]) == pytest.approx([-175.0, -185.0])


@pytest.mark.timeout(300)
def test_plot_of_a_recorded_simulation(tmp_path_factory: pytest.TempPathFactory, tmp_path: Path) -> None:
    sim = recorded_sim(tmp_path_factory)
    png = tmp_path / "run.png"
    done = subprocess.run([*U2SA, "log", "plot", str(sim.log), "-o", str(png)], cwd=REPO, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    run = read_run(sim.log)
    assert run.vehicle == "rover" and run.mission and run.waypoints and run.obstacles and run.rc_modes
    fig = build_figure(run, title=f"{run.vehicle} -- mission {run.mission}")
    assert fig._suptitle.get_text() == f"rover -- mission {run.mission}"
    track_ax, heading_ax, speed_ax, cmd_ax, mode_ax = fig.axes
    circles = [p for p in track_ax.patches if isinstance(p, patches.Circle) and not p.get_fill()]
    assert len(circles) == sum(1 for w in run.waypoints.values() if w.horizontal_threshold > 0)
    assert len(track_ax.patches) == len(circles) + len(run.obstacles)   # every obstacle drawn
    labels = {text.get_text() for text in track_ax.texts}
    assert set(run.obstacles) <= labels and all(any(uid in s for s in labels) for uid in run.waypoints)
    fig.canvas.draw()
    legend = track_ax.get_legend().get_window_extent()
    assert legend.y1 <= track_ax.get_window_extent().y0   # below the map, not on the track
    (heading,) = heading_ax.get_lines()
    ys = heading.get_ydata()
    assert len(ys) == len(run.heading) and all(abs(b - a) < 180 for a, b in zip(ys, ys[1:]))
    assert {t.get_text() for t in mode_ax.get_yticklabels()} >= {"manual"}
    assert cmd_ax.get_lines() and speed_ax.get_lines()
