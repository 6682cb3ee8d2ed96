"""What each scripted event did to the actuator outputs, from the mocks' output log.

For every event, over the window from the moment it fired to the next event (or the end of
the run), and for every output (CAN motor setpoint, PWM pulse, GPIO level, as the mock
devices saw them; :mod:`u2sa_hw.mocks.actuation`):

* ``at_event``: its value (% of full scale, or the GPIO level) and whether it was neutral;
* ``neutral_after_ms``: when it went neutral, if it was moving at the event;
* ``moved_after_ms``: when it left neutral in the window (for one moving at the event: after it
  went neutral, so a new setpoint while driving is not a move);
* ``at_end``: its value and state when the window closed.

``all_neutral_after_ms`` is when every output that was moving at the event was neutral at
once (0 when none was moving; None when that never happened in the window). ``rc_modes``
lists the RC_MODE states heard in the window, in order. ``rc_receiver_stalled_ms``: the longest
the simulated RC receiver went without handing over a frame, beyond a frame period, in the
window (None when never 50 ms or more): its thread was not run, so the RC mux heard no pulses
that long, and a NO RC SIGNAL then is the machine's load, not the event's doing.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Sequence

if TYPE_CHECKING:   # the mocks are imported only where a simulation runs
    from u2sa_hw.mocks.actuation import OutputChange, OutputLog


def _state_at(timeline: Sequence[OutputChange], t_ns: int) -> OutputChange | None:
    state = None
    for change in timeline:
        if change.t_ns > t_ns:
            break
        state = change
    return state


def _ms(t_ns: int, t0_ns: int) -> float:
    return round((t_ns - t0_ns) / 1e6, 1)


def _brief(change: OutputChange | None) -> dict[str, Any]:
    return {"value": None, "neutral": True} if change is None else {"value": change.value, "neutral": change.neutral}


def output_window(timeline: Sequence[OutputChange], start_ns: int, end_ns: int) -> dict[str, Any]:
    """One output's behaviour between *start_ns* and *end_ns* (see the module docstring)."""
    before = _state_at(timeline, start_ns)
    moving = before is not None and not before.neutral
    inside = [c for c in timeline if start_ns < c.t_ns <= end_ns]
    neutral_at = next((c.t_ns for c in inside if c.neutral), None) if moving else None
    # "moved" means left neutral: for an output moving at the event, only after it went neutral
    still_from = start_ns if not moving else neutral_at
    moved_at = None if still_from is None else next((c.t_ns for c in inside if c.t_ns > still_from and not c.neutral),
                                                     None)
    return {"at_event": _brief(before),
            "neutral_after_ms": None if neutral_at is None else _ms(neutral_at, start_ns),
            "moved_after_ms": None if moved_at is None else _ms(moved_at, start_ns),
            "at_end": _brief(_state_at(timeline, end_ns))}


def all_neutral_after(timelines: dict[str, Sequence[OutputChange]], start_ns: int, end_ns: int) -> float | None:
    """ms from *start_ns* until every output moving then was neutral at once; 0 if none was; None if never."""
    moving = {n for n, tl in timelines.items() if (s := _state_at(tl, start_ns)) is not None and not s.neutral}
    if not moving:
        return 0.0
    merged = sorted((c.t_ns, name, c.neutral) for name in moving for c in timelines[name]
                    if start_ns < c.t_ns <= end_ns)
    for t_ns, name, neutral in merged:
        if neutral:
            moving.discard(name)
        else:
            moving.add(name)
        if not moving:
            return _ms(t_ns, start_ns)
    return None


def event_effects(log: OutputLog, fired: Sequence[tuple[Any, int]], *, end_ns: int, t0_ns: int,
                  rc_modes: Sequence[tuple[int, str]] = (),
                  rc_stalls: Sequence[tuple[int, int]] = ()) -> list[dict[str, Any]]:
    """Per fired event (event, monotonic ns): its outputs' windows, all-neutral time, RC_MODE states heard, the
    RC receiver mock's longest stall (*rc_stalls*: (its end, ns beyond a frame period), monotonic ns)."""
    timelines = {name: log.timeline(name) for name in log.names()}
    results = []
    for i, (event, start_ns) in enumerate(fired):
        stop_ns = fired[i + 1][1] if i + 1 < len(fired) else end_ns
        results.append({
            "at_s": event.at_s, "action": event.action, "event": event.describe(),
            "fired_s": round((start_ns - t0_ns) / 1e9, 3),
            "outputs": {name: {"kind": log.kind(name), **output_window(tl, start_ns, stop_ns)}
                        for name, tl in timelines.items()},
            "all_neutral_after_ms": all_neutral_after(timelines, start_ns, stop_ns),
            "rc_modes": [mode for t_ns, mode in rc_modes if start_ns < t_ns <= stop_ns],
            "rc_receiver_stalled_ms": max((round(late / 1e6, 1) for t_ns, late in rc_stalls
                                           if start_ns < t_ns <= stop_ns), default=None),
        })
    return results


def final_outputs(log: OutputLog) -> dict[str, dict[str, Any]]:
    """Every output's last value and state, and how many times it changed."""
    return {name: {"kind": log.kind(name), **_brief(log.current(name)), "changes": len(log.timeline(name))}
            for name in log.names()}
