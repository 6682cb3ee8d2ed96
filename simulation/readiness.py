"""When a simulated stack can drive, and what fails a run while ``u2sa sim`` waits for it.

:func:`not_ready` lists what the pilot still waits for before handing over (services up, every IMU
calibrated at rest, no other service degraded for ``DEGRADED_GRACE_S``, a pose estimate with a
heading, a mission, the RC mux in manual), saying each service's health error once as it
changes, and raises :class:`SimFailure` for an IMU that does not calibrate within
``IMU_CALIBRATION_S``. :func:`where` says where the mission is, for a timeout's message.
"""

from __future__ import annotations

import math
from typing import Callable, Iterable

from u2sa_hw.simulation.progress import BusSnapshot

DEGRADED_GRACE_S = 20.0   # the pilot waits this long for degraded services (other than IMUs) to be ok
IMU_CALIBRATION_S = 45.0  # an IMU not calibrated at rest this long after start fails the run


class SimFailure(RuntimeError):
    """The simulation cannot go on; ``result`` is "timeout" or "failed"."""

    def __init__(self, reason: str, result: str = "failed") -> None:
        super().__init__(reason)
        self.result = result


def say_errors(snap: BusSnapshot, names: Iterable[str], said: dict[str, str], say: Callable[[str], None]) -> None:
    """Show each service's health error (a missing device and its fix) on the console once, as it changes
    (*said*: service -> the error last shown; *names*: the launcher's services)."""
    names = set(names)
    for name, (status, error, _t) in sorted(snap.health.items()):
        if status != "ok" and error and said.get(name) != error and name in names:
            said[name] = error
            say(f"  ! {name} {status}: {error}")


def not_ready(snap: BusSnapshot, *, names: list[str], imus: list[str], waited_s: float, said: dict[str, str],
              say: Callable[[str], None]) -> list[str]:
    """What the stack still lacks to drive ([] when ready), after *waited_s* since the start; *names*: its
    services, *imus*: those that calibrate at rest; SimFailure for an IMU that did not in time."""
    missing = []
    say_errors(snap, names, said, say)
    up = [n for n in names if n in snap.health and snap.health[n][0] not in ("starting", "stopping")]
    if len(up) < len(names):
        waiting = [n + (f" ({snap.health[n][1]})" if n in snap.health and snap.health[n][1] else "")
                   for n in names if n not in up]
        missing.append(f"{len(up)}/{len(names)} services up (waiting: {', '.join(waiting)})")
    calibrating = [n for n in imus if n in up and snap.health[n][0] != "ok"]
    if calibrating and waited_s >= IMU_CALIBRATION_S:
        raise SimFailure(f"IMU {', '.join(calibrating)} did not calibrate at rest within {IMU_CALIBRATION_S:g} s "
                         f"(health: {'; '.join(snap.health[n][1] or snap.health[n][0] for n in calibrating)}); "
                         "the pilot does not hand over an uncalibrated IMU")
    if calibrating:
        missing.append("IMU calibrating at rest: " + ", ".join(
            f"{n} ({snap.health[n][1] or snap.health[n][0]})" for n in calibrating))
    degraded = [n for n in up if snap.health[n][0] != "ok" and n not in imus]
    if degraded and waited_s < DEGRADED_GRACE_S:
        missing.append("degraded: " + ", ".join(f"{n} ({snap.health[n][1] or snap.health[n][0]})"
                                                for n in degraded))
    if snap.estimate is None or not math.isfinite(snap.estimate[3]):
        missing.append("no pose estimate" if snap.estimate is None else "estimate has no heading")
    if snap.status is None or snap.status.finished or snap.status.num_goals == 0:
        missing.append("no mission")
    if snap.rc is None:
        missing.append("no RC_MODE (the control system drives only in autonomous mode)")
    elif snap.rc.mode != 0:
        missing.append(f"RC mode {snap.rc.mode_name or snap.rc.mode}, not manual")
    return missing


def where(snap: BusSnapshot, goal_total: int) -> str:
    """Where the mission is (the goal, how far), or the channel still missing."""
    st = snap.status
    if st is None:
        return "MISSION_STATUS"
    distance = f", {snap.nav.distance_to_goal:.1f} m away" if snap.nav is not None else ""
    return f"goal {st.current_index + 1} of {goal_total} ({st.current_uid}{distance})"
