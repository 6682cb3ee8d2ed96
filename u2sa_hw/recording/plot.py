"""``u2sa log plot``: track, heading, speed and actuator commands of a log over time."""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

from u2sa_hw.channels import base_type
from u2sa_hw.messages import REGISTRY, MalformedMessage
from u2sa_hw.recording.log_reader import LogFile


def plot_log(src: Path | str, out: Path | str, *, channel: str = "STATE_ESTIMATE") -> dict[str, int]:
    """Draw *channel*'s track, heading and speed and every actuator's commands into a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    log = LogFile(src)
    t0: int | None = None
    track: list[tuple[float, float, float]] = []
    heading: list[tuple[float, float]] = []
    speed: list[tuple[float, float]] = []
    commands: dict[str, list[tuple[float, float]]] = defaultdict(list)
    for m in log.messages(f"{channel}|ACTUATOR_CMD"):
        t0 = m.log_time_ns if t0 is None else t0
        t = (m.log_time_ns - t0) / 1e9
        try:
            msg, _ = REGISTRY.decode(m.data, base_type(m.channel))
        except MalformedMessage:
            continue
        if m.channel == channel:
            if msg.has("x") and msg.has("y"):
                track.append((t, msg.x, msg.y))
            if msg.has("psi"):
                heading.append((t, math.degrees(msg.psi) % 360.0))
            if msg.has("x_dot") and msg.has("y_dot"):
                speed.append((t, math.hypot(msg.x_dot, msg.y_dot)))
        elif hasattr(msg, "percentage"):
            commands[msg.base.actuator_name].append((t, msg.percentage))
    fig, axes = plt.subplots(2, 2, figsize=(12, 9))
    ax = axes[0][0]
    if track:
        ax.plot([p[2] for p in track], [p[1] for p in track], "-", lw=1.5)
        ax.plot(track[0][2], track[0][1], "go", label="start")
        ax.plot(track[-1][2], track[-1][1], "rs", label="end")
        ax.legend()
    ax.set(title=f"track ({channel})", xlabel="east (m)", ylabel="north (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True)
    for ax, series, title, unit in ((axes[0][1], heading, "heading", "deg"), (axes[1][0], speed, "speed", "m/s")):
        ax.plot([p[0] for p in series], [p[1] for p in series], ".", ms=2)
        ax.set(title=title, xlabel="time (s)", ylabel=unit)
        ax.grid(True)
    ax = axes[1][1]
    for name, series in sorted(commands.items()):
        ax.plot([p[0] for p in series], [p[1] for p in series], "-", lw=1, label=name)
    if commands:
        ax.legend()
    ax.set(title="actuator commands", xlabel="time (s)", ylabel="%", ylim=(-105, 105))
    ax.grid(True)
    fig.suptitle(str(Path(src).name))
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return {"track": len(track), "heading": len(heading), "speed": len(speed),
            "commands": sum(len(s) for s in commands.values())}
