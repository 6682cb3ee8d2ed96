"""The safety chain's real-time set-up with the system calls faked: who may, which priorities, one line when not."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from u2sa_hw.install.units import COMMAND_SOURCE_KINDS, safety_dropins, unit_dropins
from u2sa_hw.launcher import Launcher
from u2sa_hw.launcher.children import u2sa_command
from u2sa_hw.realtime import (NORMAL, SAFETY_CHAIN_PRIORITIES, SIM_DEVICES_PRIORITY, SchedCalls, Schedule,
                             describe_plan, plan, priority_for)
from u2sa_hw.profile.loader import load_profile

KINDS = {"rc": "rc_mux", "wheels": "odrive_can", "vesc": "vesc_can", "rudder": "pwm_servo", "horn": "gpio_output",
         "hsm": "hsm", "gps": "gps_nmea", "control": "control", "est": "state_estimator"}


def fake(*, cap: bool = False, rtprio: int = 0, throttle: int | None = 950000,
         calls: list[tuple[int, Schedule]] | None = None, refuse: bool = False) -> SchedCalls:
    def setscheduler(pid: int, schedule: Schedule) -> None:
        if refuse:
            raise PermissionError(1, "Operation not permitted")
        if calls is not None:
            calls.append((pid, schedule))

    return SchedCalls(cap_sys_nice=lambda: cap, rlimit_rtprio=lambda: rtprio, throttle_us=lambda: throttle,
                      setscheduler=setscheduler)


def test_the_safety_chain_gets_its_priorities_and_the_rc_mux_the_highest() -> None:
    permitted = plan(calls=fake(cap=True))
    assert permitted.notice is None
    got = {name: s.priority for name, s in permitted.schedules(KINDS).items()}
    assert got == {"rc": 30, "wheels": 25, "vesc": 25, "rudder": 25, "horn": 25, "hsm": 20,
                   "gps": 0, "control": 0, "est": 0}
    assert max(SAFETY_CHAIN_PRIORITIES, key=SAFETY_CHAIN_PRIORITIES.__getitem__) == "rc_mux"
    assert all(1 <= p < 50 for p in SAFETY_CHAIN_PRIORITIES.values())   # below the kernel's threaded IRQs (50)
    assert SIM_DEVICES_PRIORITY < min(SAFETY_CHAIN_PRIORITIES.values())
    assert plan(calls=fake(rtprio=99)).ceiling == 30                  # ulimit -r high enough: as root
    assert describe_plan(permitted, {"rc": "rc_mux", "gps": "gps_nmea"}) == "real-time (SCHED_FIFO): rc 30"
    assert Schedule(30).policy == os.SCHED_FIFO and NORMAL.policy == os.SCHED_OTHER
    assert not Schedule(30).policy & getattr(os, "SCHED_RESET_ON_FORK", 0)   # the service's threads keep it


def test_not_permitted_says_so_in_one_line_and_everything_runs_normal() -> None:
    denied = plan(calls=fake(rtprio=0))
    assert denied.notice == ("real-time priority not permitted (no CAP_SYS_NICE, RLIMIT_RTPRIO 0): the safety chain "
                             "runs at normal priority; see docs/safety.md")
    assert all(s == NORMAL for s in denied.schedules(KINDS).values())


def test_a_low_rlimit_rtprio_caps_the_chain_and_says_so() -> None:
    capped = plan(calls=fake(rtprio=22))
    assert capped.notice is not None and "\n" not in capped.notice
    assert capped.notice.startswith("real-time priority capped at 22 by RLIMIT_RTPRIO (the RC mux asks 30)")
    got = {name: s.priority for name, s in capped.schedules(KINDS).items() if s.realtime}
    assert got == {"rc": 22, "wheels": 22, "vesc": 22, "rudder": 22, "horn": 22, "hsm": 20}


def test_throttling_off_or_no_realtime_leaves_everyone_normal() -> None:
    off = plan(calls=fake(cap=True, throttle=-1))
    assert off.ceiling == 0 and off.notice is not None and "kernel RT throttling is off" in off.notice
    asked = plan(enabled=False, calls=fake(cap=True))
    assert asked.ceiling == 0 and asked.notice is None           # --no-realtime: nothing to explain
    assert priority_for("gps_nmea") == 0


def test_the_sim_raises_every_thread_of_its_process_and_restores_them() -> None:
    calls: list[tuple[int, Schedule]] = []
    threads = [101, 102, 103]
    sched = fake(cap=True, calls=calls)
    sched = SchedCalls(cap_sys_nice=sched.cap_sys_nice, rlimit_rtprio=sched.rlimit_rtprio,
                       throttle_us=sched.throttle_us, setscheduler=sched.setscheduler, threads=lambda: threads)
    raised = plan(calls=sched).raise_process()
    assert calls == [(tid, Schedule(SIM_DEVICES_PRIORITY)) for tid in (101, 102, 103)] and raised.refused is None
    calls.clear()
    threads.append(104)   # started since: it inherited the raise, and is restored too
    raised.restore()
    raised.restore()      # once only
    assert calls == [(tid, NORMAL) for tid in (101, 102, 103, 104)]

    capped: list[tuple[int, Schedule]] = []
    five = fake(rtprio=5, calls=capped)
    plan(calls=SchedCalls(five.cap_sys_nice, five.rlimit_rtprio, five.throttle_us, five.setscheduler,
                          threads=lambda: [7])).raise_process()
    assert capped == [(7, Schedule(5))]
    none: list[tuple[int, Schedule]] = []
    denied = plan(calls=fake(rtprio=0, calls=none)).raise_process()
    assert none == [] and denied.refused is None                 # not permitted: the plan's notice says it
    refused = plan(calls=fake(cap=True, refuse=True)).raise_process()
    assert refused.refused == "the simulated devices run at normal priority: Operation not permitted"


def _profile(tmp_path: Path, kinds: dict[str, str]) -> Path:
    text = ['[vehicle]\nname = "rt"\nlcm_url = "udpm://239.255.76.67:7667?ttl=0"\n']
    text += [f'[services.{name}]\nkind = "{kind}"\n' for name, kind in kinds.items()]
    path = tmp_path / "vehicle.toml"
    path.write_text("\n".join(text))
    return path


def test_the_launcher_gives_each_child_its_schedule_and_says_the_notice_once(tmp_path: Path) -> None:
    profile = load_profile(_profile(tmp_path, {"rc": "rc_mux", "wheels": "odrive_can", "gps": "gps_nmea"}))
    permitted = Launcher(profile, control=False, realtime=plan(calls=fake(cap=True)), output=lambda n, line: None)
    assert {n: p.setup.schedule for n, p in permitted.processes.items()} == {
        "rc": Schedule(30), "wheels": Schedule(25), "gps": NORMAL}
    untouched = Launcher(profile, control=False, output=lambda n, line: None)
    assert all(p.setup.schedule is None for p in untouched.processes.values())   # no plan: priorities inherited

    lines: list[tuple[str, str]] = []
    denied = Launcher(profile, control=False, realtime=plan(calls=fake(rtprio=0)),
                      output=lambda n, line: lines.append((n, line)), command=lambda spec: ["/bin/true"])
    denied.start()
    try:
        assert denied.wait(30)
    finally:
        denied.stop(timeout=10)
    said = [line for name, line in lines if name == "launcher" and "real-time" in line]
    assert said == ["real-time priority not permitted (no CAP_SYS_NICE, RLIMIT_RTPRIO 0): the safety chain runs at "
                    "normal priority; see docs/safety.md"]


def test_the_units_drop_ins_carry_the_same_priorities_and_sigkill_for_command_sources(tmp_path: Path) -> None:
    profile = load_profile(_profile(tmp_path, KINDS))
    dropins = {path: text.decode() for path, text in unit_dropins(profile, pwm_services={}).items()}
    realtime = {path.split("/")[-2]: text for path, text in dropins.items() if path.endswith("/30-realtime.conf")}
    expected = {("u2sa-hsm.service" if kind == "hsm" else f"u2sa@{name}.service") + ".d": kind
                for name, kind in KINDS.items() if priority_for(kind)}
    assert set(realtime) == set(expected)
    for unit, kind in expected.items():
        lines = realtime[unit].splitlines()
        assert "[Service]" in lines and "CPUSchedulingPolicy=fifo" in lines, realtime[unit]
        assert f"CPUSchedulingPriority={SAFETY_CHAIN_PRIORITIES[kind]}" in lines
        assert not any(line.startswith("CPUSchedulingResetOnFork=") for line in lines)
    killed = {path.split("/")[-2] for path, text in dropins.items()
              if path.endswith("/31-command-source.conf") and "\nWatchdogSignal=SIGKILL\n" in text}
    assert killed == {f"u2sa@{n}.service.d" for n, k in KINDS.items() if k in COMMAND_SOURCE_KINDS}
    assert "control" in {KINDS[n] for n in KINDS if f"u2sa@{n}.service.d" in killed}   # the autonomy's commands
    assert safety_dropins("u2sa@gps.service", "gps_nmea") == {}
    template = (Path(__file__).parents[1] / "systemd/u2sa@.service").read_text()
    assert "WatchdogSignal=" not in template   # the others keep SIGABRT: their stacks in the journal


@pytest.mark.parametrize("command", ["run", "sim"])
def test_help_teaches_no_realtime(command: str) -> None:
    shown = subprocess.run([*u2sa_command(), command, "--help"], capture_output=True, text=True, timeout=60)
    assert shown.returncode == 0, shown.stderr
    text = " ".join(shown.stdout.split())
    assert "--no-realtime" in text and "SCHED_FIFO" in text and "docs/safety.md" in text
    assert "CAP_SYS_NICE" in text


def test_u2sa_sim_realtime_can_be_turned_off_by_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """$U2SA_SIM_REALTIME=off (the test suite's setting) is --no-realtime for every u2sa sim; unset, it is allowed."""
    from u2sa_hw.simulation.runner import SIM_REALTIME_ENV, sim_realtime_allowed

    monkeypatch.delenv(SIM_REALTIME_ENV, raising=False)
    assert sim_realtime_allowed()
    for value in ("off", "0", "No", " false "):
        monkeypatch.setenv(SIM_REALTIME_ENV, value)
        assert not sim_realtime_allowed(), value
    monkeypatch.setenv(SIM_REALTIME_ENV, "on")
    assert sim_realtime_allowed()
