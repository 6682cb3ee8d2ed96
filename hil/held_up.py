"""When the recording machine held a replayed service up: the windows of the log where what that service
published depended on the recording machine's load, which the log does not hold.

A service says so in its health: the RC mux counts its loop's ``stalls`` (a loop gap longer than the signal
timeout disarms it, judged on the wall clock, never in a replay) and ``timed_skipped`` (a timed message left
out for being a period behind). A replay runs on the recorded stamps and reproduces neither, so
``--compare`` reports what differs inside such a window as a note naming the window and the counters,
instead of as a difference (hil/compare.py). Everywhere else the service is compared as usual.

A window runs from the health message before a counter grew to the one where it had grown (the counters
are read once a second), widened by HELD_MARGIN_S on each side for the effects that outlast the stall (a
frame's pulses aged out, the next timed message).

A servo driver (``LOOP_AGE_BY_KIND``) says so by its loop's age in its health: one sent while the loop was
more than the limit behind (not the first of a run: its loop may not have turned yet) makes a window from
when that loop last turned to HELD_MARGIN_S after the health.

And from HELD_MARGIN_S before a service's first health saying it stops (``stopping``, ``stopped``; it says so
once it has begun to stop, later on a loaded machine) to the end: the live service took no more input then, the replayed one, stopped only after the playback, takes what was recorded after it
(an Ackermann log's servo driver, stopping with the stack, left the last commands unwritten).

So is where a GPIO driver read its edges late: each recorded edge carries its kernel stamp and the time it
was tapped, and an edge tapped more than LATE_EDGE_NS after the quickest tap of the log was read that much
late by the live driver (its loop was held up); the RC mux's timed messages wait at most that long for the
edges of their frame (drivers/rc_mux_clock.TIMED_HOLD_NS), so one may have gone out without them.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

from u2sa_hw.recording.log_reader import LogFile

# service kind -> the health details that count the recording machine holding the service up
# (``checks_lost``: a service's health came too late for a pre-arm check, on the recording machine's clock)
# (a servo driver's ``rc_mode_stale``: its newest RC_MODE aged past the limit on its own clock - with the RC mux
# running, its bus handling was held up, and it then took its backlog of commands and RC_MODEs late)
# (an actuator's ``taken_late``: commands or RC_MODEs it took over 0.1 s later than its quickest lately, by their
# header stamps - its bus handling was held up, even for less than an RC_MODE takes to go stale;
# u2sa_hw/safety/late_take.py)
HELD_UP_BY_KIND: dict[str, tuple[str, ...]] = {"rc_mux": ("stalls", "timed_skipped", "checks_lost"),
                                               "pwm_servo": ("rc_mode_stale", "taken_late"),
                                               "odrive_can": ("taken_late",), "vesc_can": ("taken_late",)}
# service kind -> the loop age (s, the contract health's ``loop_age_s``) past which its loop was held up when the
# health was sent: a servo driver writes what the bus commands, in the order it takes its messages; held up, it
# took a backlog of commands late and in another order against the RC mux's (issue 24, an Ackermann recording
# under load wrote stale throttle commands for 90 ms), which no replay reproduces
LOOP_AGE_BY_KIND: dict[str, float] = {"pwm_servo": 0.1}
LATE_EDGE_NS = 50_000_000   # = u2sa_hw.drivers.rc_mux.clock.TIMED_HOLD_NS (not imported: hil reads logs, not drivers)
HELD_MARGIN_S = 0.5
# A service's health saying it stops: from then on the live service takes no more input (its bus handling has
# ended) but the replay, still running, takes the recorded messages republished after it
STOPPING = ("stopping", "stopped")
STOP_WINDOW_END = 2 ** 63 - 1
STOP_WHY = ("was stopping (its health said so: the live service took no more input, the replayed one, "
            "stopped after the playback, took what was recorded after it)")


@dataclass(frozen=True)
class HeldWindow:
    """Log times [from_ns, to_ns] where *service* was held up; *why*: the counters that grew, with their growth."""

    service: str
    from_ns: int
    to_ns: int
    why: str

    def holds(self, t_ns: int) -> bool:
        """Whether log time *t_ns* is inside the window."""
        return self.from_ns <= t_ns <= self.to_ns


def plan_windows(log: Path | str, *, kinds: Mapping[str, str], devices: Mapping[str, str], start_ns: int,
                 end_ns: int) -> dict[str, list[HeldWindow]]:
    """Every held-up window of a replay's services (*kinds*: service -> kind; *devices*: GPIO device -> its
    service), from one pass over the log."""
    gauges = {name: LOOP_AGE_BY_KIND[kind] for name, kind in kinds.items() if kind in LOOP_AGE_BY_KIND}
    return _scan(log, held_up_counters(kinds), devices, start_ns=start_ns, end_ns=end_ns, loop_ages=gauges,
                 stopping=set(kinds))


def held_up_counters(kinds: Mapping[str, str]) -> dict[str, tuple[str, ...]]:
    """service -> its held-up counters, for the services (*kinds*: name -> kind) whose kind has any."""
    return {name: HELD_UP_BY_KIND[kind] for name, kind in kinds.items() if kind in HELD_UP_BY_KIND}


def held_windows(log: Path | str, counters: Mapping[str, tuple[str, ...]], *, start_ns: int | None = None,
                 end_ns: int | None = None, loop_ages: Mapping[str, float] | None = None) -> dict[str, list[HeldWindow]]:
    """service -> the windows of *log* where its health counters (*counters*) grew, or its health said its loop
    was more than *loop_ages* [service] s behind; services with none left out."""
    return _scan(log, counters, {}, start_ns=start_ns, end_ns=end_ns, loop_ages=loop_ages)


def late_edge_windows(log: Path | str, devices: Mapping[str, str], *, start_ns: int,
                      end_ns: int) -> dict[str, list[HeldWindow]]:
    """service -> windows (merged) around the recorded GPIO edges (*devices*: device -> service) its driver
    tapped more than LATE_EDGE_NS later than the quickest tap of the log (tap time is wall clock, the stamp
    monotonic: only the difference from the quickest means something)."""
    return _scan(log, {}, devices, start_ns=start_ns, end_ns=end_ns)


def _scan(log: Path | str, counters: Mapping[str, tuple[str, ...]], devices: Mapping[str, str], *,
          start_ns: int | None, end_ns: int | None,
          loop_ages: Mapping[str, float] | None = None, stopping: set[str] | None = None) -> dict[str, list[HeldWindow]]:
    """The counter and loop-age windows of *counters*' and *loop_ages*' services, the stop windows of
    *stopping*'s and the late-edge windows of *devices* in one read."""
    from u2sa_hw import lcmtypes as t
    from u2sa_hw.messages import REGISTRY, MalformedMessage

    loop_ages, stopping = loop_ages or {}, stopping or set()
    wanted = (["U2SA_HEALTH"] if counters or loop_ages or stopping else []) + [rf"RAW\.{re.escape(d)}" for d in devices]
    if not wanted:
        return {}
    margin = int(HELD_MARGIN_S * 1e9)
    first = start_ns
    last: dict[str, tuple[int, dict[str, int]]] = {}   # service -> (log time, counters) of its latest health
    lags: list[tuple[str, int, int]] = []               # (service, log time, tap time - kernel stamp)
    runs: dict[str, str | None] = {}                    # service -> the start (started_us) of its latest health
    out: dict[str, list[HeldWindow]] = {}
    for m in LogFile(log).messages("|".join(wanted)):
        if end_ns is not None and m.log_time_ns > end_ns + margin:
            break
        if m.channel != "U2SA_HEALTH":
            if (start_ns is None or m.log_time_ns >= start_ns) and (end_ns is None or m.log_time_ns <= end_ns):
                try:
                    rec, _ = REGISTRY.decode(m.data)
                except MalformedMessage:
                    continue
                if type(rec).__name__ == "RawGpioEdge" and rec.header.timestamp_us:
                    lag = int(rec.header.timestamp_us) * 1000 - int(rec.kernel_timestamp_ns)
                    lags.append((devices[m.channel[4:]], m.log_time_ns, lag))
            continue
        first = m.log_time_ns if first is None else first
        try:
            health = t.Health.decode(m.data)
        except Exception:  # noqa: BLE001 - a malformed health message says nothing about load
            continue
        if health.name in stopping and health.status in STOPPING and m.log_time_ns >= (start_ns or 0):
            stopping.discard(health.name)   # its first such health only
            out.setdefault(health.name, []).append(HeldWindow(health.name, m.log_time_ns - margin, STOP_WINDOW_END, STOP_WHY))
        names = counters.get(health.name)
        if not names and health.name not in loop_ages:
            continue
        details = {kv.key: kv.value for kv in health.details}
        age = _seconds(details.get("loop_age_s"))
        run, runs[health.name] = runs.get(health.name), details.get("started_us")
        # a service's first health of a run can come before its loop first turned: its age is the start-up's
        if health.name in loop_ages and age > loop_ages[health.name] and run == details.get("started_us"):
            why = f"its loop {age:.2f} s behind"
            out.setdefault(health.name, []).append(
                HeldWindow(health.name, m.log_time_ns - int(age * 1e9) - margin, m.log_time_ns + margin, why))
        if not names:
            continue
        now = {n: _count(details.get(n)) for n in names}
        before_t, before = last.get(health.name, (first, dict.fromkeys(names, 0)))
        grown = {n: now[n] - before.get(n, 0) for n in names if now[n] > before.get(n, 0)}
        if grown:
            why = ", ".join(f"{n} +{d}" for n, d in grown.items())
            window = HeldWindow(health.name, before_t - margin, m.log_time_ns + margin, why)
            out.setdefault(health.name, []).append(window)
        last[health.name] = (m.log_time_ns, now)
    for service, windows in _late_edges(lags, margin).items():
        out.setdefault(service, []).extend(windows)
    return out


def _seconds(text: str | None) -> float:
    try:
        return float(text or 0.0)
    except ValueError:
        return 0.0


def _count(text: str | None) -> int:
    try:
        return int(text or 0)
    except ValueError:
        return 0


def _late_edges(lags: list[tuple[str, int, int]], margin: int) -> dict[str, list[HeldWindow]]:
    """Windows (merged) around the edges tapped more than LATE_EDGE_NS later than their service's quickest."""
    quickest: dict[str, int] = {}
    for service, _t, lag in lags:
        quickest[service] = min(quickest.get(service, lag), lag)
    out: dict[str, list[HeldWindow]] = {}
    for service, t, lag in lags:
        if lag - quickest[service] <= LATE_EDGE_NS:
            continue
        windows = out.setdefault(service, [])
        if windows and windows[-1].to_ns >= t - margin:
            w = windows[-1]
            windows[-1] = HeldWindow(service, w.from_ns, t + margin, w.why)
        else:
            windows.append(HeldWindow(service, t - margin, t + margin,
                                      f"its edges read over {LATE_EDGE_NS / 1e6:.0f} ms late"))
    return out
