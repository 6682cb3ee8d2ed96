"""``u2sa log plot`` of a recorded simulation: the page holds the map with the waypoints, their thresholds
and the obstacles, the unwrapped heading, the commands and the RC mode panel; the legend is off the track
and the title names the vehicle and the mission (artists checked, not pixels). The failsafe panel keeps
the failsafes per source, as every holder does, and geodetic objects land on the map about the origin."""

from __future__ import annotations

import math
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest
from conftest import REPO, U2SA
from recorded_sim import recorded_sim

pytest.importorskip("matplotlib")

from matplotlib import patches  # noqa: E402

from u2sa_hw import lcmtypes as t  # noqa: E402
from u2sa_hw.geo import ned_to_geodetic  # noqa: E402
from u2sa_hw.recording.mcap_log import McapLogWriter, RunInfo  # noqa: E402
from u2sa_hw.recording.plot import FAILSAFE_COLOUR, failsafe_spans, log_figure, unwrapped_degrees  # noqa: E402
from u2sa_hw.profile.vehicle import Origin  # noqa: E402

ORIGIN = Origin(29.19, -81.05, 10.0)
PROFILE = b'[vehicle]\nname = "rover"\norigin = { lat = 29.19, lon = -81.05, alt = 10.0 }\n'


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

    fig, run = log_figure(sim.log)   # the very figure `u2sa log plot` saves
    assert run.vehicle == "rover" and run.mission and run.waypoints and run.obstacles and run.rc_modes
    assert fig._suptitle.get_text() == f"rover -- mission {run.mission} -- {sim.log.name} ({run.end:.0f} s)"
    track_ax, heading_ax, speed_ax, cmd_ax, mode_ax = fig.axes
    circles = [p for p in track_ax.patches if isinstance(p, patches.Circle) and not p.get_fill()]
    assert len(circles) == sum(1 for w in run.waypoints.values() if w.horizontal_threshold > 0)
    assert run.fence is not None and [a.name for a in run.fence.areas] == ["yard", "pond"]   # the example's fence
    # every obstacle and fence area drawn
    assert len(track_ax.patches) == len(circles) + len(run.obstacles) + len(run.fence.areas)
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


def failsafe(source: str, active: bool, reason: str = "", service: str = "") -> bytes:
    msg = t.Failsafe()
    msg.header.source, msg.active, msg.reason, msg.service = source, active, reason, service
    return msg.encode()


def red_spans(ax: Any) -> list[tuple[float, float]]:
    """The x extent of every red (failsafe) span drawn on *ax* (axvspan: a Rectangle, or a Polygon before 3.9)."""
    import matplotlib.colors as mcolors

    red = mcolors.to_rgb(FAILSAFE_COLOUR)
    spans = []
    for p in ax.patches:
        if mcolors.to_rgb(p.get_facecolor()) == pytest.approx(red):
            xs = [p.get_x(), p.get_x() + p.get_width()] if hasattr(p, "get_width") else [x for x, _y in p.get_xy()]
            spans.append((min(xs), max(xs)))
    return sorted(spans)


def test_failsafe_panel_holds_each_source_until_it_or_the_operator_clears_it(tmp_path: Path) -> None:
    """hsm holds from 3 s to 8 s while an e-stop raises and releases inside (4-5 s): one span 3-8 s, not 3-5 s.
    Then an e-stop from 10 s: an hsm clear (it holds nothing) and an operator clear of hsm leave it held; the
    operator's '*' clears it at 13 s. A GEODETIC circle in WORLD is placed about the log's origin."""
    path = tmp_path / "fs.mcap"
    writer = McapLogWriter(tmp_path, path=path, run=RunInfo(vehicle="rover", attachments={"vehicle.toml": PROFILE}))
    t0 = time.time_ns()
    at = lambda s: t0 + int(s * 1e9)  # noqa: E731
    s = t.StateInformation().set(x=0.0, y=0.0, psi=0.0)
    s.sensor_name, s.reference_frame = "state_estimator", "NED"
    writer.write("STATE_ESTIMATE", s.encode(), at(0))
    mode = t.RcMode()
    mode.mode_name, mode.autonomy_enabled = "autonomous", True
    writer.write("RC_MODE", mode.encode(), at(0.5))
    circle = t.Circle()
    base = circle.base.base
    lat, lon, _alt = ned_to_geodetic(40.0, -20.0, 0.0, origin=ORIGIN)
    base.uid, base.reference_frame, base.x, base.y, base.z = "buoy", "GEODETIC", lat, lon, ORIGIN.alt
    circle.radius = 3.0
    writer.write("WORLD", circle.encode(), at(1))
    events = [(3, failsafe("hsm", True, "gps stale")), (4, failsafe("hsm", True, "gps stale")),
              (4, failsafe("estop", True, "pressed")), (5, failsafe("estop", False)),
              (6, failsafe("hsm", True, "gps stale")), (8, failsafe("hsm", False)),
              (10, failsafe("estop", True, "pressed")), (11, failsafe("hsm", False)),
              (12, failsafe("operator", False, service="hsm")), (13, failsafe("operator", False, service="*"))]
    for sec, data in events:
        writer.write("FAILSAFE", data, at(sec))
    writer.write("STATE_ESTIMATE", s.encode(), at(15))
    writer.close()

    fig, run = log_figure(path)
    spans = failsafe_spans(run)
    assert [x for a, b, _who in spans for x in (a, b)] == pytest.approx([3, 8, 10, 13])
    assert spans[0][2] == "hsm: gps stale; estop: pressed" and spans[1][2] == "estop: pressed"
    mode_ax = fig.axes[-1]
    assert [x for span in red_spans(mode_ax) for x in span] == pytest.approx([3, 8, 10, 13])
    assert any("hsm: gps stale" in text.get_text() for text in mode_ax.texts)
    (buoy,) = run.obstacles.values()
    assert (buoy.base.base.x, buoy.base.base.y) == pytest.approx((40.0, -20.0), abs=0.01)
    track_ax = fig.axes[0]
    (patch,) = [p for p in track_ax.patches if isinstance(p, patches.Circle)]
    assert patch.center == pytest.approx((-20.0, 40.0), abs=0.01) and patch.get_radius() == 3.0
    assert fig._suptitle.get_text() == "rover -- mission (none in the log) -- fs.mcap (15 s)"
    fig.savefig(tmp_path / "fs.png")
