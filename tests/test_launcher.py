"""The local launcher with real `u2sa run` processes, real children and real LCM multicast."""

from __future__ import annotations

import os
import re
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import psutil
import pytest
from conftest import wait_until
from supervision_helpers import BROKEN_CONFIG_ERROR, break_config, launch, write_profile  # noqa: F401 - a fixture

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.launcher import Launcher, LauncherBusy, LauncherClient, LauncherError, RestartPolicy, SupervisedProcess
from u2sa_hw.launcher.children import u2sa_command
from u2sa_hw.launcher.policy import REFUSED_EXIT
from u2sa_hw.service.bus_handlers import DUPLICATE_EXIT, DUPLICATE_PROBE_S, PROBE_ENV
from u2sa_hw.profile.loader import load_profile


def _alive(pid: int) -> bool:
    """True while *pid* runs (a zombie nobody reaped yet counts as dead)."""
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def _health_pids(bus: BusClient) -> dict[str, set[int]]:
    seen: dict[str, set[int]] = {}
    lock = threading.Lock()

    def on_health(_c: str, msg: t.Health) -> None:
        with lock:
            seen.setdefault(msg.name, set()).add(msg.pid)

    bus.transport.subscribe(ch.HEALTH, t.Health, on_health)
    return seen


def test_killed_child_restarts_with_new_run_id_and_sigint_stops_all(tmp_path: Path, lcm_url: str, bus: BusClient,
                                                                     launch: Any) -> None:
    health = _health_pids(bus)
    lp = launch(write_profile(tmp_path, lcm_url, {"est_a": "state_estimator", "est_b": "state_estimator"}),
                "--grace", "5")
    status = wait_until(lambda: (s := lp.status()) and all(v["state"] == "running" for v in s.values()) and s,
                        timeout=20, message="both services running under the launcher")
    pid_a, pid_b = status["est_a"]["pid"], status["est_b"]["pid"]
    assert status["est_a"]["run_id"] == 1 and status["est_b"]["run_id"] == 1
    wait_until(lambda: pid_a in health.get("est_a", ()) and pid_b in health.get("est_b", ()), timeout=20,
               message="health from both children")

    os.kill(pid_a, signal.SIGKILL)
    after = wait_until(lambda: (s := lp.status()) and s["est_a"]["run_id"] == 2 and s["est_a"]["state"] == "running"
                       and s, timeout=20, message="est_a restarted with run id 2")
    new_pid = after["est_a"]["pid"]
    assert new_pid != pid_a and after["est_a"]["restarts"] == 1
    assert after["est_b"]["run_id"] == 1 and after["est_b"]["pid"] == pid_b
    wait_until(lambda: new_pid in health.get("est_a", ()), timeout=20, message="health from the restarted est_a")
    out = lp.output
    assert "est_a killed by SIGKILL" in out and "restarting in" in out
    assert re.search(r"^est_a +\| .*est_a \(state_estimator\) started", out, re.MULTILINE)

    lp.proc.send_signal(signal.SIGINT)
    assert lp.proc.wait(timeout=20) == 0
    assert not _alive(new_pid) and not _alive(pid_b)
    out = lp.output
    assert re.search(r"est_a exited with status 0 .*\(stopped\)", out)
    assert re.search(r"est_b exited with status 0 .*\(stopped\)", out)
    assert not (tmp_path / "data" / "launcher.sock").exists()


def test_crash_looping_service_backs_off_then_launcher_gives_up(tmp_path: Path, lcm_url: str, launch: Any) -> None:
    profile = write_profile(tmp_path, lcm_url, {"est": "state_estimator", "broken": "state_estimator"})
    break_config(tmp_path, "broken")
    lp = launch(profile, "--force", "--backoff", "0.05", "--give-up-after", "4", "--grace", "5")   # past u2sa check
    assert lp.proc.wait(timeout=60) == 1
    out = lp.output
    delays = [float(d) for d in re.findall(r"broken exited with status 1 .*restarting in ([0-9.]+) s", out)]
    assert delays == [0.05, 0.1, 0.2], out
    assert "broken exited with status 1" in out and "giving up after 4 quick deaths in a row" in out
    assert re.search(rf"^broken +\| .*{BROKEN_CONFIG_ERROR}", out, re.MULTILINE)   # the child's own error, prefixed
    assert "exit 1: given up on broken" in out
    # the healthy service was stopped cleanly, not left behind
    assert re.search(r"^launcher +\| est (exited with status 0|killed by SIGTERM) .*\(stopped\)", out, re.MULTILINE), out


def test_restart_policy_doubles_caps_decays_and_gives_up() -> None:
    policy = RestartPolicy(initial_backoff_s=0.5, max_backoff_s=3.0, quick_death_s=10.0, give_up_after=5)
    quick, delays = 0, []
    for _ in range(4):
        quick, delay = policy.after_death(quick, uptime_s=1.0)
        delays.append(delay)
    assert delays == [0.5, 1.0, 2.0, 3.0] and quick == 4
    assert not policy.gives_up(quick)
    # 25 s of healthy uptime forgives two quick deaths: the delay halves twice
    quick, delay = policy.after_death(quick, uptime_s=25.0)
    assert (quick, delay) == (2, 1.0)
    quick, _ = policy.after_death(quick, uptime_s=100.0)
    assert quick == 0
    for _ in range(5):
        quick, _ = policy.after_death(quick, uptime_s=0.1)
    assert policy.gives_up(quick)
    assert not RestartPolicy(give_up_after=0).gives_up(1000)
    with pytest.raises(ValueError, match="initial_backoff_s"):
        RestartPolicy(initial_backoff_s=5.0, max_backoff_s=1.0)


SLOW_CRASH = ("import os, socket, sys, time\n"
              "addr = os.environ['NOTIFY_SOCKET']\n"
              "with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:\n"
              "    s.sendto(b'READY=1', '\\0' + addr[1:] if addr.startswith('@') else addr)\n"
              "time.sleep(float(os.environ['CRASH_AFTER_S']))\n"
              "print('crashing now', flush=True)\n"
              "sys.exit(5)\n")


def test_a_service_that_crashes_after_a_healthy_looking_start_is_given_up(tmp_path: Path, lcm_url: str) -> None:
    # Each run outlives quick_death_s, so the quick-death rule alone would restart it forever.
    profile = load_profile(write_profile(tmp_path, lcm_url, {"slow": "state_estimator"}))
    lines: list[tuple[str, str]] = []
    policy = RestartPolicy(initial_backoff_s=0.05, quick_death_s=0.1, give_up_after=2, max_failures=3,
                           failure_window_s=120.0)
    launcher = Launcher(profile, policy=policy, control=False, output=lambda n, line: lines.append((n, line)),
                        command=lambda spec: [sys.executable, "-c", SLOW_CRASH], env={"CRASH_AFTER_S": "0.3"})
    launcher.start()
    try:
        assert launcher.wait(60), "the launcher never gave up on a service crashing every 0.3 s"
    finally:
        launcher.stop(timeout=10)
    assert launcher.exit_code == 1 and launcher.failed == ["slow"]
    said = [line for name, line in lines if name == "launcher"]
    assert sum("slow exited with status 5" in line for line in said) == 3
    assert any("restarting in 0.05 s (quick deaths: 0, failures: 2/3 within 120 s)" in line for line in said), said
    assert any("giving up after 3 failed exits within 120 s" in line for line in said), said
    (status,) = launcher.status()
    assert status.state == "failed" and status.quick_deaths == 0 and status.failures == 3
    assert status.reason == "3 failed exits within 120 s, last exited with status 5"
    assert lines.count(("slow", "crashing now")) == 3


NEVER_READY_CRASH = ("import time, sys\n"
                     "time.sleep(0.3)\n"   # longer than quick_death_s: a slow start on a busy machine
                     "sys.exit(4)\n")


def test_a_run_that_dies_before_it_is_ready_is_a_quick_death_however_long_it_took(tmp_path: Path,
                                                                                   lcm_url: str) -> None:
    # Healthy uptime counts from READY=1: a child that never came up backs off and is given up on
    # by the quick-death rule, whatever a loaded machine made its start cost.
    profile = load_profile(write_profile(tmp_path, lcm_url, {"slow": "state_estimator"}))
    lines: list[tuple[str, str]] = []
    policy = RestartPolicy(initial_backoff_s=0.05, quick_death_s=0.1, give_up_after=3, max_failures=0)
    launcher = Launcher(profile, policy=policy, control=False, output=lambda n, line: lines.append((n, line)),
                        command=lambda spec: [sys.executable, "-c", NEVER_READY_CRASH])
    launcher.start()
    try:
        assert launcher.wait(60), "the launcher never gave up on a service that never became ready"
    finally:
        launcher.stop(timeout=10)
    said = [line for name, line in lines if name == "launcher"]
    delays = [float(d) for d in re.findall(r"slow exited with status 4 .*never ready.*restarting in ([0-9.]+) s",
                                            "\n".join(said))]
    assert delays == [0.05, 0.1], said
    assert any("giving up after 3 quick deaths in a row" in line for line in said), said


def test_failures_outside_the_window_are_forgotten() -> None:
    now = [0.0]
    policy = RestartPolicy(initial_backoff_s=0.0, quick_death_s=1.0, give_up_after=0, max_failures=3,
                           failure_window_s=60.0)
    proc = SupervisedProcess("svc", ["true"], policy=policy, clock=lambda: now[0])
    for at in (0.0, 40.0, 80.0, 120.0):        # one failure every 40 s: at most 2 within any 60 s
        now[0] = at
        account = proc.failed_to_spawn("no such file")
        assert proc.state == "backoff", account
    assert proc.status().failures == 2
    now[0] = 130.0
    proc.failed_to_spawn("no such file")
    assert proc.state == "failed" and "3 failed exits within 60 s" in proc.reason
    proc.restart("operator", grace_s=1.0)       # a fresh start forgets the failures
    assert proc.state == "backoff" and proc.status().failures == 0
    assert not RestartPolicy(max_failures=0).too_many_failures(10_000)
    with pytest.raises(ValueError, match="failure_window_s > 0"):
        RestartPolicy(failure_window_s=0.0)


def test_run_gives_up_by_failures_within_the_window_with_quick_deaths_off(tmp_path: Path, lcm_url: str,
                                                                         launch: Any) -> None:
    profile = write_profile(tmp_path, lcm_url, {"broken": "state_estimator"})
    break_config(tmp_path, "broken")
    lp = launch(profile, "--force", "--backoff", "0.05", "--give-up-after", "0", "--max-failures", "3",
                "--failure-window", "600")
    assert lp.proc.wait(timeout=60) == 1
    out = lp.output
    assert out.count("broken exited with status 1") == 3
    assert "giving up after 3 failed exits within 600 s" in out and "exit 1: given up on broken" in out


def test_run_help_documents_both_give_up_rules() -> None:
    from u2sa_hw.cli import build_parser

    run = build_parser()._subparsers._group_actions[0].choices["run"]   # noqa: SLF001 - the real parser
    text = run.format_help()
    assert "--max-failures N" in text and "--failure-window S" in text and "crashes every 6 s" in text


STUBBORN = ("import signal, sys, time\n"
            "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
            "print('ignoring SIGTERM', flush=True)\n"
            "time.sleep(120)\n")


def test_library_sigkill_after_grace_control_socket_and_single_owner(tmp_path: Path, lcm_url: str) -> None:
    profile = load_profile(write_profile(tmp_path, lcm_url, {"stubborn": "state_estimator"}))
    lines: list[tuple[str, str]] = []
    deaths: list[str] = []
    launcher = Launcher(profile, grace_s=0.5, output=lambda n, line: lines.append((n, line)),
                        on_death=lambda status, account: deaths.append(f"{status.name}:{status.state}:{account}"),
                        command=lambda spec: [sys.executable, "-c", STUBBORN])
    launcher.start()
    try:
        wait_until(lambda: ("stubborn", "ignoring SIGTERM") in lines, timeout=10, message="the child's output")
        with pytest.raises(LauncherBusy, match="already running this vehicle"):
            Launcher(profile, output=lambda n, line: None).start()

        client = LauncherClient(tmp_path / "data" / "launcher.sock")
        first = client.status()[0]
        assert first["run_id"] == 1 and first["state"] == "running"
        with pytest.raises(LauncherError, match="no service 'nope'"):
            client.restart("nope")
        client.restart("stubborn", reason="test asked")
        wait_until(lambda: client.status()[0]["run_id"] == 2, timeout=10, message="run 2 after a restart request")
        assert any("stubborn did not acknowledge the stop within 0.5 s (no STOPPING=1): SIGKILL" in line for _, line in lines)
        assert deaths and deaths[0].startswith("stubborn:backoff:killed by SIGKILL; restarting now")
        assert client.status()[0]["quick_deaths"] == 0     # a requested restart is no quick death
        wait_until(lambda: lines.count(("stubborn", "ignoring SIGTERM")) == 2, timeout=10, message="run 2 ready")
    finally:
        assert launcher.stop(timeout=10) == 0
    assert launcher.finished.is_set()
    assert sum("did not acknowledge the stop within" in line for _, line in lines) == 2


def test_killed_launcher_takes_its_children_and_leaves_a_reusable_socket(tmp_path: Path, lcm_url: str,
                                                                        launch: Any) -> None:
    profile = write_profile(tmp_path, lcm_url, {"est": "state_estimator"})
    first = launch(profile)
    pid = wait_until(lambda: (s := first.status()) and s["est"]["state"] == "running" and s["est"]["pid"],
                     timeout=20, message="est running")
    first.proc.kill()
    first.proc.wait(timeout=10)
    wait_until(lambda: not _alive(pid), timeout=10, message="the orphaned child to die with its launcher")
    assert (tmp_path / "data" / "launcher.sock").exists()   # left behind by the SIGKILL
    second = launch(profile)
    wait_until(lambda: (s := second.status()) and s["est"]["state"] == "running", timeout=20,
               message="a new launcher on the same vehicle")


def test_a_recorder_starts_first_and_the_others_once_it_is_ready(tmp_path: Path, lcm_url: str) -> None:
    """READY=1 reaches the launcher's own NOTIFY_SOCKET with the sender's pid; the others wait for the recorder's."""
    profile = load_profile(write_profile(tmp_path, lcm_url, {"est": "state_estimator", "rec": "recorder",
                                                              "world": "world_modeler"}))
    lines: list[tuple[str, str]] = []
    launcher = Launcher(profile, control=False, output=lambda n, line: lines.append((n, line)))
    assert launcher.start_first == ["rec"]
    launcher.start()
    try:
        wait_until(lambda: all(s.ready for s in launcher.status()), timeout=30,
                   message="every child to report READY=1 to the launcher")
        said = [line for name, line in lines if name == "launcher"]
        order = [next(i for i, line in enumerate(said) if line.startswith(prefix))
                 for prefix in ("rec started", "rec ready after", "starting the others now that rec is ready")]
        assert order == sorted(order), said
        others = [i for i, line in enumerate(said) if line.startswith(("est started", "world started"))]
        assert len(others) == 2 and min(others) > order[1], said
        assert all(s.status_text for s in launcher.status())   # STATUS= arrives too
    finally:
        assert launcher.stop(timeout=30) == 0
    # and it stops last, once the others have exited: its log holds their stop
    said = [line for name, line in lines if name == "launcher"]
    stopped = {n: next(i for i, line in enumerate(said) if line.startswith(f"{n} ") and line.endswith("(stopped)"))
               for n in ("rec", "est", "world")}
    assert stopped["rec"] > max(stopped["est"], stopped["world"]), said
    assert any("rec once the others have exited" in line for line in said), said
    rec_told = [i for i, (name, line) in enumerate(lines) if name == "rec" and "stopped" in line.lower()]
    others_gone = max(i for i, (name, line) in enumerate(lines) if name == "launcher" and line.endswith("(stopped)")
                      and not line.startswith("rec "))
    assert rec_told and min(rec_told) > others_gone, lines


def test_a_first_service_that_never_gets_ready_holds_the_others_only_for_first_wait_s(tmp_path: Path,
                                                                                      lcm_url: str) -> None:
    profile = load_profile(write_profile(tmp_path, lcm_url, {"rec": "recorder", "est": "state_estimator"}))
    lines: list[tuple[str, str]] = []
    mute = [sys.executable, "-c", "import time; time.sleep(60)"]   # runs, never says READY=1
    launcher = Launcher(profile, control=False, first_wait_s=2.0, grace_s=1.0,
                        output=lambda n, line: lines.append((n, line)),
                        command=lambda spec: mute if spec.name == "rec" else
                        [*u2sa_command(), "service", spec.name, "--vehicle", str(profile.path)])
    cpu_before = time.process_time()
    launcher.start()
    try:
        wait_until(lambda: any(line.startswith("rec not ready") for _n, line in lines), timeout=30,
                   message="the hold to end")
        # While holding, the loop sleeps until the hold ends (it used to spin: a whole core for first_wait_s).
        assert time.process_time() - cpu_before < 1.0
        wait_until(lambda: {s.name: s.ready for s in launcher.status()} == {"rec": False, "est": True}, timeout=30,
                   message="the estimator started and ready while the muted recorder never is")
        assert ("launcher", "rec not ready after 2 s: starting the others anyway") in lines
    finally:
        launcher.stop(timeout=30)


REFUSES = ("import sys\n"
           "print('another one of my name is on the bus', flush=True)\n"
           "sys.exit(3)\n")


def test_a_service_that_refuses_to_start_is_never_restarted(tmp_path: Path, lcm_url: str) -> None:
    # Exit status 3 is a refusal (u2sa_hw.service.bus_handlers): a restart would find the same, as under
    # systemd's RestartPreventExitStatus=3. Its line is printed once and the launcher stops.
    assert REFUSED_EXIT == DUPLICATE_EXIT == 3
    profile = load_profile(write_profile(tmp_path, lcm_url, {"dup": "state_estimator", "est": "state_estimator"}))
    lines: list[tuple[str, str]] = []
    policy = RestartPolicy(initial_backoff_s=0.0, quick_death_s=5.0, give_up_after=5, max_failures=10)
    launcher = Launcher(profile, policy=policy, control=False, grace_s=1.0,
                        output=lambda n, line: lines.append((n, line)),
                        command=lambda spec: [sys.executable, "-c", REFUSES if spec.name == "dup" else
                                              "import time; time.sleep(60)"])
    launcher.start()
    try:
        assert launcher.wait(60), "the launcher kept going after a refusal"
    finally:
        launcher.stop(timeout=10)
    assert launcher.exit_code == 1 and launcher.failed == ["dup"]
    assert lines.count(("dup", "another one of my name is on the bus")) == 1
    said = [line for name, line in lines if name == "launcher"]
    assert sum(line.startswith("dup started") for line in said) == 1
    assert any(line.startswith("dup exited with status 3") and "refused to start" in line and "not restarted" in line
               for line in said), said
    assert not any("restarting in" in line for line in said), said
    status = {s.name: s for s in launcher.status()}
    assert status["dup"].state == "failed" and status["dup"].reason.startswith("refused to start")
    assert status["dup"].run_id == 1 and status["est"].state == "stopped"


def test_the_unit_file_prevents_the_restart_of_a_refusal_too() -> None:
    unit = (Path(__file__).resolve().parents[1] / "systemd" / "u2sa@.service").read_text()
    assert f"RestartPreventExitStatus={REFUSED_EXIT}" in unit.splitlines()


def test_a_second_run_of_the_vehicle_on_its_bus_refuses_once(tmp_path: Path, lcm_url: str, launch: Any,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """The same profile from a second directory (its own data_dir, so its own control socket): its service
    finds the first run's one on the bus, says so once, and nothing is restarted."""
    monkeypatch.setenv(PROBE_ENV, str(DUPLICATE_PROBE_S))   # the default probe, then the watch after start
    (tmp_path / "one").mkdir()
    (tmp_path / "two").mkdir()
    first = launch(write_profile(tmp_path / "one", lcm_url, {"est": "state_estimator"}))
    pid = wait_until(lambda: (s := first.status()) and s["est"]["ready"] and s["est"]["pid"], timeout=60,
                     message="the first run's service ready")
    second = launch(write_profile(tmp_path / "two", lcm_url, {"est": "state_estimator"}))
    assert second.proc.wait(timeout=120) == 1
    out = second.output
    assert out.count("already runs on this bus") == 1 and f"pid {pid}" in out, out
    assert re.search(r"^launcher +\| est exited with status 3 .*refused to start.*not restarted", out, re.MULTILINE)
    assert out.count("est started, pid") == 1 and "restarting in" not in out
    assert "exit 1: est refused to start" in out
    assert first.proc.poll() is None and first.status()["est"]["pid"] == pid
