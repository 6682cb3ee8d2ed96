#!/usr/bin/env python3
"""The budget bench: the example vehicle's services held to a CPU budget, stepped down.

A Raspberry Pi-class board shares its cores with the team's own work. This bench asks how
little CPU the stack needs before its mission or its safety deadlines give: it holds the
example ground vehicle's 12 services to a cgroup CPU quota (a share of one core), with the
mock devices and the simulator (the ``u2sa sim`` process) outside the budget, and steps the
budget down (``--budgets``, default 100, 60, 40, 30, 20 % of one core).

At each step it plays, ``--runs`` times each (a fresh budget group per run):
  mission        the example mission (as ``make sim``): completed?, its time, start-up,
                 autonomy losses (the pilot re-engages; more than 3 fail the run), and the
                 stack's CPU: from the cgroup's own usage counter (cpuacct / cpu.stat),
                 so every restart and both scheduling classes count, over the whole run
                 (start-up included) and while driving; "sim" is the u2sa sim process
                 (mocks, simulator) plus the services; "thr" the share of quota periods
                 in which the budget throttled the group.
  rc_loss        the RC link dropped mid-mission: ms from each loss to every moving
                 wheel output neutral (target <= 200 ms), as bench/failsafe.py measures it.
  manual_switch  the pilot's switch to manual: ms to the autonomous outputs stopped
                 (target <= 50 ms).

How to read it: the HEADLINE is the lowest budget at which everything holds: the missions
completed, no autonomy loss, every failsafe event within its target (the maximum, not the
median); a higher budget that did not hold is named beside it as noise. Below the table
each step that did not hold says why; an autonomy loss right after the simulated RC
receiver's own stall is a note, not counted, unless --whole-sim. CPU figures are % of one
core of this machine; a Pi 4 core runs Python several times slower, so a budget here is a
smaller share of a Pi.

Real time (cgroup v1 with RT group scheduling): the safety chain runs SCHED_FIFO when
permitted, and a CFS quota does not hold real-time tasks, so the budget sets the group's
``cpu.rt_runtime_us`` to the same share; the usage figure counts both. cgroup v2 has no RT
budget: use ``--no-realtime`` there for an honest figure. ``--whole-sim`` puts the whole
``u2sa sim`` process in the budget instead. ``--selftest`` checks that a budget limits.

Needs root (it creates cgroups ``u2sa-sbc-<pid>`` and moves processes; every group is
removed at the end, Ctrl-C included). It prints figures; its exit status says only that it ran.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import resource
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from bench.cpu_budget import (BudgetError, CpuBudget, Hierarchy, detect, parse_budgets,  # noqa: E402
                              read_usage_ns, remove_stale, require_root, selftest)
from bench.sbc_figures import (FAILSAFE, STALL_MS, RunResult, Step, describe, headline, result_of,  # noqa: E402
                                table)

VEHICLE = REPO / "examples" / "ground_vehicle" / "vehicle.toml"
PR_SET_PDEATHSIG = 1
KINDS = ("mission", *FAILSAFE)
ECHO = ("ready after", "reached at", "autonomy lost", "re-arming", "completed in", "FAILED", "TIMED OUT", "real-time",
        "normal priority", "refused", "cannot join", "all neutral after", "never neutral")


# -- one run, in a child process of its own (``--_one-run``) ----------------------------------
def one_run(spec: dict[str, Any]) -> int:
    """Play one sim run; write the CPU windows beside its summary (``sbc-run.json``)."""
    from u2sa_hw.simulation.progress import ProgressLine
    from u2sa_hw.simulation.runner import SimOptions, SimRun
    from u2sa_hw.bus.udp_ports import private_lcm_url, private_udp_port

    signal.signal(signal.SIGINT, signal.default_int_handler)   # even when started ignoring it (in the background)
    usage_file, with_runner = Path(spec["usage_file"]), spec["with_runner"]
    samples: list[tuple[float, int, int]] = []
    done = threading.Event()

    def sample() -> None:
        samples.append((time.monotonic(), read_usage_ns(usage_file), time.process_time_ns()))

    def sampler() -> None:
        while not done.wait(0.5):
            sample()

    scenario = FAILSAFE[spec["kind"]].scenario if spec["kind"] in FAILSAFE else None
    out = Path(spec["out"])
    options = SimOptions(vehicle=VEHICLE, out=out, lcm_url=private_lcm_url(), can_port=private_udp_port(),
                         timeout_s=spec["timeout_s"], scenario=REPO / scenario if scenario else None,
                         service_cgroup=Path(spec["service_cgroup"]), realtime=spec["realtime"])
    run = SimRun(options, progress=ProgressLine(sys.stdout, interactive=False, plain_every_s=15))
    sample()
    thread = threading.Thread(target=sampler, daemon=True)
    thread.start()
    run.run()
    done.set()
    thread.join()
    sample()

    def window(t0: float | None, t1: float | None) -> dict[str, float] | None:
        if t0 is None or t1 is None:
            return None
        a = min(samples, key=lambda s: abs(s[0] - t0))
        b = min(samples, key=lambda s: abs(s[0] - t1))
        wall, used, own = b[0] - a[0], (b[1] - a[1]) / 1e9, (b[2] - a[2]) / 1e9
        if wall <= 0:
            return None
        stack, whole = (used - own, used) if with_runner else (used, used + own)
        return {"wall_s": wall, "stack_pct": 100 * stack / wall, "sim_pct": 100 * whole / wall}

    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0, t1 = run.record.t_engage or samples[0][0], run.record.t_end or samples[-1][0]
    stalls = run.mocks.rc_stalls() if run.mocks is not None else []
    figures = {"run": window(samples[0][0], samples[-1][0]), "drive": window(run.record.t_engage, run.record.t_end),
               "rusage_stack_pct": 100 * (children.ru_utime + children.ru_stime) / (samples[-1][0] - samples[0][0]),
               "drive_end_epoch": time.time() - (time.monotonic() - t1),
               "rc_stalls_ms": [ns / 1e6 for end, ns in stalls if ns >= STALL_MS * 1e6 and t0 <= end / 1e9 <= t1]}
    ends = [end / 1e9 - t0 for end, ns in stalls if ns >= STALL_MS * 1e6]   # s after engaging, as interruptions
    figures["losses_after_rc_stall"] = sum(1 for i in run.record.interruptions
                                           if any(-1.5 <= i["at_s"] - e <= 1.0 for e in ends))
    (out / "sbc-run.json").write_text(json.dumps(figures, indent=1))
    return 0


def play(*, hierarchy: Hierarchy, percent: float, kind: str, out: Path, args: argparse.Namespace) -> RunResult:
    """One run at *percent* in a fresh budget group: the child's lines worth seeing echoed, its figures."""
    out.mkdir(parents=True, exist_ok=True)
    for stale in ("summary.json", "sbc-run.json"):
        (out / stale).unlink(missing_ok=True)
    with CpuBudget(hierarchy, percent, whole_sim=args.whole_sim) as budget:
        usage_file, with_runner = budget.usage_file()
        spec = {"kind": kind, "out": str(out), "timeout_s": args.timeout, "service_cgroup": str(budget.group),
                "usage_file": str(usage_file), "with_runner": with_runner, "realtime": not args.no_realtime}

        def preexec() -> None:
            os.setpgid(0, 0)   # Ctrl-C reaches the bench only, which stops the child in order
            ctypes.CDLL(None).prctl(PR_SET_PDEATHSIG, int(signal.SIGINT))   # ... and so does a SIGKILLed bench
            budget.runner_join()

        proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--_one-run", json.dumps(spec)],
                                cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                env=os.environ | {"PYTHONUNBUFFERED": "1"}, preexec_fn=preexec)
        try:
            with (out / "sbc.log").open("w") as log:
                for line in proc.stdout:
                    log.write(line)
                    if any(marker in line for marker in ECHO):
                        print(f"      {line.rstrip()[:150]}", flush=True)
            proc.wait()
        except BaseException:
            proc.send_signal(signal.SIGINT)   # SimRun finishes on Ctrl-C: services and mocks stopped
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
            raise
        periods = budget.throttling()
    say_launcher_lines(out / "services.log")
    return result_of(kind, out, periods, exit_code=proc.returncode)


_SAID: set[str] = set()


def say_launcher_lines(log: Path) -> None:
    """Echo, once per bench, what the launcher said about real-time priority and the cgroup."""
    try:
        lines = log.read_text(errors="replace").splitlines()
    except OSError:
        return
    for line in lines:
        name, _, text = line.partition("|")
        if name.strip() == "launcher" and any(k in text for k in ("real-time", "cgroup", "refused", "priority")):
            text = text.strip().replace(f"-{os.getpid()}", "-<pid>")
            if text not in _SAID:
                _SAID.add(text)
                print(f"      launcher: {text}", flush=True)


def main(argv: list[str] | None = None) -> int:
    """Step the budget down and print the table and the headline."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--budgets", default="100,60,40,30,20",
                        help="%% of one core, highest first (default %(default)s)")
    parser.add_argument("--runs", type=int, default=1, help="runs of each kind per budget (default 1)")
    parser.add_argument("--whole-sim", action="store_true", help="the whole u2sa sim process in the budget, mocks too")
    parser.add_argument("--no-realtime", action="store_true",
                        help="the services and the sim may not take a real-time priority (for cgroup v2)")
    parser.add_argument("--kinds", default=",".join(KINDS), help="which runs per step (default %(default)s)")
    parser.add_argument("--timeout", type=float, default=240.0, help="each run's timeout, s (default 240)")
    parser.add_argument("--out", type=Path, default=REPO / "bench-out" / "sbc", help="run output (default %(default)s)")
    parser.add_argument("--selftest", action="store_true", help="only check that a budget limits busy loops")
    parser.add_argument("--_one-run", dest="one_run", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one_run:
        return one_run(json.loads(args.one_run))
    try:
        budgets = parse_budgets(args.budgets)
        kinds = [k for k in args.kinds.split(",") if k]
        if args.runs < 1:
            raise ValueError("--runs must be at least 1")
        if unknown := set(kinds) - set(KINDS):
            raise ValueError(f"unknown kinds {sorted(unknown)} (choose from {', '.join(KINDS)})")
        require_root()
        hierarchy = detect()
    except ValueError as exc:
        parser.error(str(exc))
    except BudgetError as exc:
        sys.exit(f"bench/sbc.py: {exc}")
    for signum in (signal.SIGINT, signal.SIGTERM):   # cleanup as on Ctrl-C, also when started in the background
        signal.signal(signum, signal.default_int_handler)
    print(f"u2sa-hw budget bench: {hierarchy.describe()}")
    print(f"  {os.cpu_count()} CPUs, Python {sys.version.split()[0]}, load average "
          f"{' / '.join(f'{x:.1f}' for x in os.getloadavg())}; budgets {', '.join(f'{b:g}' for b in budgets)} % "
          f"of one core; {'the whole u2sa sim' if args.whole_sim else 'the services only'} in the budget; "
          f"real-time {'off (--no-realtime)' if args.no_realtime else 'as permitted'}")
    if not hierarchy.realtime and not args.no_realtime:
        print("  no RT budget here: a CFS quota does not hold real-time tasks, so the safety chain's SCHED_FIFO time "
              "is outside the budget (still counted in the usage); --no-realtime for an honest budget")
    for path in remove_stale(hierarchy):
        print(f"  removed {path}, left by a bench that no longer runs")
    if args.selftest:
        for line in selftest(hierarchy, budgets):
            print("  " + line, flush=True)
        return 0
    from u2sa_hw.bus.run_keys import use_run_key

    use_run_key()
    steps: list[Step] = []
    total, n, started = len(budgets) * len(kinds) * args.runs, 0, time.monotonic()
    try:
        for percent in budgets:
            step = Step(percent, whole_sim=args.whole_sim)
            steps.append(step)
            for index in range(args.runs):
                for kind in kinds:
                    n += 1
                    print(f"[{percent:g} % | {n}/{total} | {time.monotonic() - started:5.0f} s | load "
                          f"{os.getloadavg()[0]:.1f}] {kind} run {index + 1}/{args.runs}", flush=True)
                    t0 = time.monotonic()
                    mode = "whole" if args.whole_sim else "services"
                    run = play(hierarchy=hierarchy, percent=percent, kind=kind, args=args,
                               out=args.out / f"{mode}-{percent:g}" / f"{kind}-{index + 1}")
                    step.runs.append(run)
                    print(f"    {describe(run)} [{time.monotonic() - t0:.0f} s]", flush=True)
            print(f"  {percent:g} %: " + ("; ".join(step.problems()) or "everything holds")
                  + "".join(f"; {note}" for note in step.notes()), flush=True)
    except KeyboardInterrupt:
        print("\ninterrupted: the figures so far", flush=True)
        if steps and not steps[-1].runs:
            steps.pop()
    if not steps:
        return 1
    print(f"\nload average at the end {' / '.join(f'{x:.1f}' for x in os.getloadavg())}; "
          f"{time.monotonic() - started:.0f} s in all; runs under {args.out}")
    for line in table(steps):
        print(line)
    for step in sorted(steps, key=lambda s: -s.percent):
        if problems := step.problems() + step.notes():
            print(f"  {step.percent:g} %: " + "; ".join(problems))
    print(headline(steps, whole_sim=args.whole_sim)
          + ("" if set(kinds) == set(KINDS) else f" [only {', '.join(kinds)} runs: the rest not judged]"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
