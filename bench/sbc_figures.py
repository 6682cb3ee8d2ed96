"""bench/sbc.py's figures: one run's results from its files, a step's verdict, the table and the headline.

Pure functions of the runs' outputs (``summary.json``, ``sbc-run.json``, ``services.log``), kept
apart from the cgroup and process work so tests can feed them tables of results.
"""

from __future__ import annotations

import json
import re
import statistics
from collections import Counter
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

from bench.failsafe import CASES, Measure, timings

FAILSAFE = {c.name: c for c in CASES if c.name in ("rc_loss", "manual_switch")}
LOST = re.compile(r"\| (\S+) .*check lost while autonomous: (\w+)")
STALL_MS = 50.0   # a simulated RC receiver stall this long nears the mux's 100 ms no-signal limit


@dataclass
class RunResult:
    """One run's figures (CPU figures: % of one core; None where the run did not get that far)."""

    kind: str
    result: str
    reason: str = ""
    mission_time_s: float | None = None
    startup_s: float | None = None
    losses: int = 0
    times_ms: list[float] = field(default_factory=list)
    never: int = 0   # failsafe events whose moving outputs never went neutral
    idle: int = 0    # failsafe events with nothing moving at the event: not a measurement
    stack_pct: float | None = None
    stack_drive_pct: float | None = None
    sim_drive_pct: float | None = None
    periods: tuple[int, int] = (0, 0)
    restarts: int = 0
    causes: dict[str, int] = field(default_factory=dict)   # pre-arm check -> times lost while autonomous
    rusage_pct: float | None = None   # the services' own getrusage over the run: a check on the cgroup figure
    rc_stalls: int = 0   # the simulated RC receiver's own stalls of STALL_MS or more while driving
    sim_losses: int = 0  # autonomy losses right after such a stall: the simulator's, unless it is in the budget


@dataclass
class Step:
    """The runs at one budget."""

    percent: float
    runs: list[RunResult] = field(default_factory=list)
    whole_sim: bool = False   # the simulated devices are in the budget: their stalls are the budget's too

    def of(self, kind: str) -> list[RunResult]:
        """This step's runs of *kind*."""
        return [r for r in self.runs if r.kind == kind]

    def problems(self) -> list[str]:
        """Why this step does not hold; empty when everything holds."""
        out = []
        for run in self.of("mission"):
            if run.result != "completed":
                out.append(f"mission {run.result}: {run.reason}")
        losses = sum(r.losses for r in self.of("mission"))
        if not self.whole_sim:
            losses -= sum(r.sim_losses for r in self.of("mission"))
        if losses > 0:
            causes: Counter[str] = Counter()
            for run in self.of("mission"):
                causes.update(run.causes)
            why = ", ".join(f"{check} x{n}" for check, n in causes.most_common())
            stalls = sum(r.rc_stalls for r in self.of("mission"))
            out.append(f"{losses} autonomy loss{'es' * (losses > 1)}" + (f" (checks lost: {why})" if why else "")
                       + (f" while the simulated RC receiver itself stalled {stalls} times for "
                          f">= {STALL_MS:g} ms" if stalls else ""))
        for name, case in FAILSAFE.items():
            target = case.measures[0].target_ms
            runs = self.of(name)
            for run in runs:
                if run.result not in ("completed", "played"):   # a failsafe case is a scenario: played to its end
                    out.append(f"{name} {run.result}: {run.reason}")
            times = [t for r in runs for t in r.times_ms]
            never = sum(r.never for r in runs)
            if never:
                out.append(f"{name}: {never} event(s) whose outputs never went neutral")
            if runs and not times:
                out.append(f"{name}: no measurement")
            elif times and target is not None and max(times) > target:
                out.append(f"{name}: max {max(times):.0f} ms > {target:g} ms")
        return out

    def notes(self) -> list[str]:
        """What was seen but does not count against the budget."""
        sim = sum(r.sim_losses for r in self.of("mission"))
        if self.whole_sim or not sim:
            return []
        return [f"{sim} autonomy loss{'es' * (sim > 1)} right after the simulated RC receiver (outside the budget) "
                f"stalled for >= {STALL_MS:g} ms: the machine's load, not counted"]


def headline(steps: list[Step], *, whole_sim: bool = False) -> str:
    """The lowest budget at which everything holds; what gave above it (noise) and below it."""
    what = "the whole u2sa sim (mocks and simulator included)" if whole_sim else \
        "the services (mocks and simulator outside the budget)"
    ordered = sorted(steps, key=lambda s: -s.percent)
    held = [s for s in ordered if not s.problems()]
    if not held:
        return f"HEADLINE: nothing held, not even at {ordered[0].percent:g} % of one core for {what}: " + \
            "; ".join(ordered[0].problems())
    lowest = held[-1]
    text = f"HEADLINE: everything holds down to {lowest.percent:g} % of one core for {what}"
    above = [f"{s.percent:g} % ({'; '.join(s.problems())})" for s in ordered if s.percent > lowest.percent
             and s.problems()]
    if above:
        text += f"; yet not at {', '.join(above)}: noise at a budget that did not bind, rerun with --runs 3"
    below = [s for s in ordered if s.percent < lowest.percent]
    if below:
        text += f"; at {below[0].percent:g} %: " + "; ".join(below[0].problems())
    elif ordered[-1] is lowest:
        text += " (the lowest budget tried)"
    return text


def _fmt(value: float | None, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _mean(values: list[float | None]) -> float | None:
    present = [v for v in values if v is not None]
    return statistics.fmean(present) if present else None


def table(steps: list[Step]) -> list[str]:
    """The figures, one row per budget."""
    rc, manual = (FAILSAFE[n].measures[0].target_ms for n in FAILSAFE)
    lines = [f"{'budget':>7} {'mission':>15} {'start':>6} {'losses':>6} {f'RC loss<={rc:g}':>13} "
             f"{f'manual<={manual:g}':>13} {'stack %':>8} {'driving':>8} {'sim %':>6} {'thr %':>6}  holds",
             f"{'% core':>7} {'done, time s':>15} {'s':>6} {'':>6} {'med/max ms':>13} {'med/max ms':>13} "
             f"{'run':>8} {'stack %':>8} {'drive':>6} {'':>6}"]
    for step in sorted(steps, key=lambda s: -s.percent):
        missions = step.of("mission")
        measured = missions or step.runs   # CPU from the mission runs, the nominal load, when there are some
        done = sum(r.result == "completed" for r in missions)
        mtime = _mean([r.mission_time_s for r in missions if r.result == "completed"])
        cells = []
        for name in FAILSAFE:
            times = [t for r in step.of(name) for t in r.times_ms]
            never = sum(r.never for r in step.of(name))
            cells.append((f"{statistics.median(times):.0f}/{max(times):.0f}" if times else "-") + ("!" * bool(never)))
        periods = sum(r.periods[0] for r in measured)
        throttled = 100.0 * sum(r.periods[1] for r in measured) / periods if periods else None
        lines.append(f"{step.percent:>5g} % {f'{done}/{len(missions)} {_fmt(mtime)}':>15} "
                     f"{_fmt(_mean([r.startup_s for r in missions])):>6} {sum(r.losses for r in missions):>6} "
                     f"{cells[0]:>13} {cells[1]:>13} {_fmt(_mean([r.stack_pct for r in measured])):>8} "
                     f"{_fmt(_mean([r.stack_drive_pct for r in measured])):>8} "
                     f"{_fmt(_mean([r.sim_drive_pct for r in measured])):>6} {_fmt(throttled):>6}  "
                     f"{'no' if step.problems() else 'yes'}")
    return lines


def result_of(kind: str, out: Path, periods: tuple[int, int], *, exit_code: int) -> RunResult:
    """A RunResult from the run's summary.json and sbc-run.json."""
    try:
        summary = json.loads((out / "summary.json").read_text())
    except (OSError, ValueError):
        return RunResult(kind, "failed", f"no summary (exit {exit_code}; see {out / 'sbc.log'})", periods=periods)
    figures = json.loads((out / "sbc-run.json").read_text()) if (out / "sbc-run.json").exists() else {}
    run, drive = figures.get("run") or {}, figures.get("drive") or {}
    times: list[float] = []
    misses = never = 0
    if kind in FAILSAFE:
        measure: Measure = FAILSAFE[kind].measures[0]
        times, misses = timings(summary, measure)
        never = sum(1 for e in summary.get("scenario", {}).get("events", []) if e["action"] == measure.action
                    and measure.match in e["event"] and e["all_neutral_after_ms"] is None)
    return RunResult(kind, summary["result"], summary.get("reason", ""), summary.get("mission_time_s"),
                     summary.get("startup_s"), len(summary.get("autonomy_interruptions") or []), times, never,
                     misses - never,
                     run.get("stack_pct"), drive.get("stack_pct"), drive.get("sim_pct"), periods,
                     sum(s.get("restarts", 0) for s in (summary.get("services") or {}).values()),
                     lost_checks(out / "services.log", until=figures.get("drive_end_epoch")),
                     figures.get("rusage_stack_pct"), len(figures.get("rc_stalls_ms", [])),
                     figures.get("losses_after_rc_stall", 0))


def lost_checks(log: Path, *, until: float | None = None) -> dict[str, int]:
    """Pre-arm check -> how often the RC mux dropped autonomy for it (its "check lost" lines up to *until*, epoch s).

    *until*: the end of driving; services that stop after it are not lost checks.
    """
    try:
        text = log.read_text(errors="replace")
    except OSError:
        return {}
    return dict(Counter(m.group(2) for m in LOST.finditer(text) if until is None or _epoch(m.group(1)) <= until))


def _epoch(stamp: str) -> float:
    try:
        return datetime.fromisoformat(stamp).timestamp()
    except ValueError:
        return 0.0


def describe(run: RunResult) -> str:
    """One progress line for a finished run."""
    text = run.result
    if run.kind == "mission":
        text += f", mission {_fmt(run.mission_time_s)} s, start-up {_fmt(run.startup_s)} s"
        text += f", {run.losses} autonomy losses"
    else:
        text += f", {' '.join(f'{t:.0f}' for t in run.times_ms) or 'no'} ms"
        text += f", {run.never} never neutral" if run.never else ""
        text += f", {run.idle} with nothing moving (not measured)" if run.idle else ""
    text += f", stack {_fmt(run.stack_pct)} % of one core over the run"
    if run.rc_stalls:
        text += f", the simulated RC receiver stalled {run.rc_stalls} times >= {STALL_MS:g} ms"
    if run.stack_pct is not None and run.rusage_pct is not None and abs(run.stack_pct - run.rusage_pct) > 2.0:
        text += f" (but {run.rusage_pct:.1f} % by the services' own getrusage: is every service in the group?)"
    if run.restarts:
        text += f", {run.restarts} restarts"
    return text + (f" ({run.reason})" if run.reason else "")
