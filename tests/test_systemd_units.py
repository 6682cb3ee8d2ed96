"""The units under a real systemd: booted as PID 1 of a private namespace (tests/systemd_ns.py).

`u2sa install --root` stages a vehicle with three state estimators, a recorder (named
``rec``: its drop-in follows the kind, not the name) and one service that cannot start;
systemd boots straight into u2sa.target, with journald. Checked: every unit reaches
active through READY (Type=notify) as the user u2sa with the device groups, its output in
the journal; SIGKILL -> restarted and publishing health again; SIGSTOP (a hang) -> the
watchdog kills it (systemd's journal says so) and it is restarted; a crash loop ends at
the start limit (failed); stopping u2sa.target stops every service cleanly and leaves the
recorder's file in /var/lib/u2sa/recordings a complete, indexed MCAP; poweroff ends the
namespace. `systemd-analyze verify` passes on every unit file.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from mcap.reader import make_reader  # noqa: E402
from staged_code import HIDDEN_FROM_UNITS, u2sa_command, u2sa_inside  # noqa: E402
from systemd_ns import SystemdNamespace, cannot_boot_reason, stage_root, wait_until  # noqa: E402

from u2sa_hw import channels as ch  # noqa: E402
from u2sa_hw import lcmtypes as t  # noqa: E402
from u2sa_hw.bus.client import BusClient  # noqa: E402
from u2sa_hw.bus.udp_ports import private_udp_port  # noqa: E402

REASON = cannot_boot_reason()
pytestmark = pytest.mark.skipif(REASON is not None, reason=f"systemd cannot boot here: {REASON}")

SERVICES = ("est_a", "est_b", "est_c")
RECORDER = "rec"
KINDS = {**{name: "state_estimator" for name in SERVICES}, RECORDER: "recorder"}
UNIT_FILES = ("u2sa@.service", "u2sa.target", "u2sa-hsm.service", "u2sa-multicast-lo.service")


def write_profile(path: Path, port: int, *, recorder: bool = False) -> Path:
    """A vehicle of three estimators (and a recorder), one service whose kind does not exist (not enabled)."""
    lines = ["[vehicle]", 'name = "systemd-test"', "system_id = 9",
             f'lcm_url = "udpm://239.255.76.67:{port}?ttl=0"', ""]
    for name in SERVICES:
        lines += [f"[services.{name}]", 'kind = "state_estimator"', ""]
    if recorder:
        # A low disk floor: the test's disk may be fuller than a vehicle's.
        lines += [f"[services.{RECORDER}]", 'kind = "recorder"', "settings = { min_free_mb = 10.0 }", ""]
    lines += ["[services.broken]", 'kind = "no_such_kind"', "enabled = false", ""]
    path.write_text("\n".join(lines))
    return path


class HealthWatch:
    """The latest Health message of each service, from real LCM."""

    def __init__(self, url: str) -> None:
        self.client = BusClient(url)
        self.latest: dict[str, Any] = {}
        self.lock = threading.Lock()
        self.client.transport.subscribe(ch.HEALTH, t.Health, self._on_health)

    def _on_health(self, _channel: str, msg: Any) -> None:
        with self.lock:
            self.latest[msg.name] = msg

    def pid_of(self, name: str) -> int:
        """The PID in the latest health of *name* (0 before any)."""
        with self.lock:
            msg = self.latest.get(name)
        return msg.pid if msg is not None else 0

    def forget(self, name: str) -> None:
        """Drop what was seen of *name*, to wait for fresh messages."""
        with self.lock:
            self.latest.pop(name, None)


@pytest.fixture(scope="module")
def staged(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    base = tmp_path_factory.mktemp("systemd")
    port = private_udp_port()
    profile = write_profile(base / "vehicle.toml", port, recorder=True)
    root = stage_root(base / "root")
    done = subprocess.run([*u2sa_command(root), "install", "--vehicle", str(profile), "--root", str(root),
                           "--venv", "shared"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    # The check's word on the disabled service 'broken' (an unknown kind, there to crash-loop) is a warning.
    assert "warning: " in done.stderr and "no_such_kind" in done.stderr
    return {"root": root, "url": f"udpm://239.255.76.67:{port}?ttl=0"}


def recordings(root: Path) -> list[Path]:
    """The recorder's files (the staged /var is the namespace's /var)."""
    return sorted((root / "var/lib/u2sa/recordings").glob("*.mcap"))


@pytest.fixture(scope="module")
def ns(staged: dict[str, Any]) -> Any:
    namespace = SystemdNamespace(staged["root"], unit="u2sa.target")
    namespace.boot()
    yield namespace
    namespace.poweroff()


@pytest.fixture(scope="module")
def health(staged: dict[str, Any]) -> Any:
    watch = HealthWatch(staged["url"])
    yield watch
    watch.client.close()


def test_systemd_analyze_verify_passes_on_every_unit(staged: dict[str, Any]) -> None:
    root = staged["root"]
    units = root / "etc/systemd/system"
    # The units name /opt/u2sa/venv/bin/u2sa: verify in a mount namespace where the staged /opt is /opt.
    script = (f'mount --make-rprivate / && mount --bind "{root}/opt" /opt && cd "{units}" && '
              f"systemd-analyze verify --man=no ./u2sa@est_a.service ./u2sa@{RECORDER}.service "
              + " ".join(f"./{u}" for u in UNIT_FILES if u != "u2sa@.service"))
    done = subprocess.run(["unshare", "--mount", "sh", "-c", script], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert "u2sa" not in done.stderr, done.stderr  # warnings about our units are failures too


def test_the_shared_venv_imports_code_the_sandboxed_units_can_see(staged: dict[str, Any]) -> None:
    """From a checkout under /tmp or a home, what the venv imports is the copy staged in /opt."""
    probe = ("import u2sa_hw, u2sa_hw.drivers, u2sa_hw.hil, u2sa_hw.mocks, lcm; from u2sa_hw import drivers, hil, mocks; "
             "print('\\n'.join(m.__file__ for m in (u2sa_hw, drivers, hil, mocks, lcm)))")
    script = f'mount --bind "{staged["root"]}/opt" /opt && cd / && exec /opt/u2sa/venv/bin/python -c "{probe}"'
    done = subprocess.run(["unshare", "--mount", "--propagation", "private", "sh", "-c", script],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    files = done.stdout.split()
    assert len(files) == 5 and not [f for f in files if f.startswith(HIDDEN_FROM_UNITS)], files


def test_every_unit_reaches_active_through_ready_as_u2sa(ns: SystemdNamespace, staged: dict[str, Any],
                                                         health: HealthWatch) -> None:
    for name, kind in KINDS.items():
        ns.wait_active(f"u2sa@{name}.service")
        props = ns.show(f"u2sa@{name}.service", "Type", "StatusText", "User", "WatchdogUSec")
        # Type=notify is only active after READY=1; STATUS= is the service's own line.
        assert props["Type"] == "notify"
        assert props["StatusText"] == f"{name} ({kind}) running"
        assert props["WatchdogUSec"] == "2s"
        # Output goes to journald under the unit's identifier.
        started = f"{name} ({kind}) started, pid"
        assert wait_until(lambda n=name, s=started: s in ns.journal("-t", f"u2sa-{n}"), timeout=10), \
            ns.journal_hint(f"u2sa@{name}.service")
    assert ns.state("u2sa.target") == "active/active"
    assert ns.state("u2sa-multicast-lo.service") == "active/exited"
    assert ns.state("u2sa@broken.service").startswith("inactive")
    passwd = {line.split(":")[0]: line.split(":") for line in (staged["root"] / "etc/passwd").read_text().splitlines()}
    group_file = (staged["root"] / "etc/group").read_text()
    groups = {line.split(":")[0]: line.split(":")[2] for line in group_file.splitlines()}
    status = Path(f"/proc/{ns.host_pid(ns.main_pid('u2sa@est_a.service'))}/status").read_text()
    uid = next(line.split()[1] for line in status.splitlines() if line.startswith("Uid:"))
    sup = next(line.split()[1:] for line in status.splitlines() if line.startswith("Groups:"))
    assert uid == passwd["u2sa"][2]
    assert {groups["dialout"], groups["i2c"], groups["gpio"]} <= set(sup)
    assert wait_until(lambda: all(health.pid_of(n) for n in SERVICES), timeout=10), health.latest.keys()


def test_sigkill_is_restarted_and_publishes_again(ns: SystemdNamespace, health: HealthWatch) -> None:
    unit = "u2sa@est_a.service"
    old = ns.wait_active(unit)
    restarts = int(ns.show(unit, "NRestarts")["NRestarts"])
    os.kill(ns.host_pid(old), signal.SIGKILL)
    new = ns.wait_active(unit, not_pid=old, timeout=20)
    assert int(ns.show(unit, "NRestarts")["NRestarts"]) == restarts + 1
    assert wait_until(lambda: health.pid_of("est_a") == new, timeout=10), \
        f"no health from the restarted est_a (pid {new}); last pid {health.pid_of('est_a')}"


def test_sigstop_hang_is_killed_by_the_watchdog_and_restarted(ns: SystemdNamespace, health: HealthWatch) -> None:
    unit = "u2sa@est_b.service"
    old = ns.wait_active(unit)
    host_old = ns.host_pid(old)
    os.kill(host_old, signal.SIGSTOP)
    new = ns.wait_active(unit, not_pid=old, timeout=30)
    assert not Path(f"/proc/{host_old}").exists() or "zombie" in Path(f"/proc/{host_old}/status").read_text()
    assert wait_until(lambda: health.pid_of("est_b") == new, timeout=10)
    # systemd's record of why: the watchdog, not an exit of the service. (systemd sends SIGCONT
    # with the SIGABRT, so the stopped process wakes and faulthandler puts its stacks in the journal.)
    why = ("u2sa@est_b.service: Watchdog timeout (limit 2s)!", f"Killing process {old} (u2sa) with signal SIGABRT",
           "u2sa@est_b.service: Failed with result 'watchdog'.")
    assert wait_until(lambda: all(line in ns.journal("-u", unit) for line in why), timeout=10), ns.journal("-u", unit)
    log = ns.run("cat", "/var/log/u2sa/est_b.log", check=False).stdout
    assert log.count("est_b (state_estimator) started, pid") == 2, log


def test_status_shows_each_unit_next_to_the_hsm_view(ns: SystemdNamespace, staged: dict[str, Any]) -> None:
    status = ["/opt/u2sa/venv/bin/u2sa", "status", "--vehicle", "/etc/u2sa/vehicle.toml", "--json"]
    alone = ns.run(*status, "--timeout", "0.5", check=False)
    report = json.loads(alone.stdout)
    assert alone.returncode == 0, alone.stderr
    assert report["hsm"] is None and "no SystemHealth on U2SA_SYSTEM_HEALTH" in report["hsm_note"]
    # A stand-in for the HSM (its own task's service) publishes the system view.
    client = BusClient(staged["url"])
    stop = threading.Event()

    def publish() -> None:
        msg = t.SystemHealth()
        msg.summary = "3 services ok"
        state = t.ServiceState()
        state.name, state.state, state.restarts, state.last_error = "est_a", "ok", 1, "killed by SIGKILL"
        msg.services, msg.num_services = [state], 1
        while not stop.is_set():
            client.publish(ch.SYSTEM_HEALTH, msg)
            stop.wait(0.2)

    thread = threading.Thread(target=publish, daemon=True)
    thread.start()
    try:
        done = ns.run(*status, "--timeout", "5", check=False)
    finally:
        stop.set()
        thread.join()
        client.close()
    report = json.loads(done.stdout)
    units = {u["unit"]: u for u in report["units"]}
    assert units["u2sa@est_a.service"]["active"] == "active"
    assert units["u2sa@est_a.service"]["restarts"] == ns.show("u2sa@est_a.service", "NRestarts")["NRestarts"]
    assert units["u2sa@est_a.service"]["hsm"] == {"state": "ok", "restarts": 1, "last_error": "killed by SIGKILL",
                                                   "heartbeat_age_s": 0.0, "data_age_s": 0.0}
    assert units["u2sa@est_b.service"]["hsm"] == {}
    assert report["hsm"] == {"failsafe": False, "summary": "3 services ok"}


def test_the_hsm_sandbox_may_restart_other_units(ns: SystemdNamespace, staged: dict[str, Any]) -> None:
    """u2sa-hsm.service (uid 0, no capabilities, sandboxed) can still restart a service via systemctl."""
    dropin = staged["root"] / "etc/systemd/system/u2sa-hsm.service.d"
    dropin.mkdir()
    # Same sandbox, but the program is a single systemctl call instead of the HSM service.
    (dropin / "test.conf").write_text("[Service]\nType=oneshot\nRestart=no\nWatchdogSec=0\nExecStart=\n"
                                      "ExecStart=/bin/systemctl restart u2sa@est_c.service\n")
    ns.systemctl("daemon-reload")
    try:
        old = ns.wait_active("u2sa@est_c.service")
        done = ns.systemctl("start", "u2sa-hsm.service", check=False)
        assert done.returncode == 0, (done.stderr, ns.journal_hint("u2sa-hsm.service"))
        ns.wait_active("u2sa@est_c.service", not_pid=old)
    finally:
        for f in dropin.iterdir():
            f.unlink()
        dropin.rmdir()
        ns.systemctl("daemon-reload")


def _thread_policies(host_pid: int) -> set[tuple[int, int]]:
    """(policy, rt_priority) of every thread of *host_pid*, from /proc/PID/task/TID/stat (fields 41 and 40)."""
    found = set()
    for stat in Path(f"/proc/{host_pid}/task").glob("*/stat"):
        fields = stat.read_text().rpartition(")")[2].split()   # fields from 3 on: state is [0]
        found.add((int(fields[41 - 3]), int(fields[40 - 3])))
    return found


def test_a_safety_chain_unit_runs_fifo_in_every_thread_and_a_hung_one_gets_sigkill(ns: SystemdNamespace,
                                                                                    staged: dict[str, Any]) -> None:
    """est_c gets the drop-ins an rc_mux service gets: CPUSchedulingPolicy= holds under RestrictRealtime=yes and
    the @resources filter (systemd sets it before them), the threads inherit it, and the watchdog sends SIGKILL."""
    from u2sa_hw.install.units import safety_dropins

    unit = "u2sa@est_c.service"
    written = []
    for path, text in safety_dropins(unit, "rc_mux").items():
        target = staged["root"] / path.lstrip("/")
        target.parent.mkdir(exist_ok=True)   # it exists: est_c starts after the recorder (20-after-recorder.conf)
        target.write_bytes(text)
        written.append(target)
    ns.systemctl("daemon-reload")
    try:
        old = ns.wait_active(unit)
        ns.systemctl("restart", unit)
        pid = ns.wait_active(unit, not_pid=old)
        host = ns.host_pid(pid)
        assert wait_until(lambda: len(list(Path(f"/proc/{host}/task").iterdir())) > 1, timeout=10)
        assert _thread_policies(host) == {(1, 30)}, ns.journal_hint(unit)   # SCHED_FIFO 30, every thread
        os.kill(host, signal.SIGSTOP)
        ns.wait_active(unit, not_pid=pid, timeout=30)
        why = (f"Killing process {pid} (u2sa) with signal SIGKILL", f"{unit}: Failed with result 'watchdog'.")
        assert wait_until(lambda: all(line in ns.journal("-u", unit) for line in why), timeout=10), \
            ns.journal("-u", unit)
    finally:
        for target in written:
            target.unlink()
        ns.systemctl("daemon-reload")
        ns.systemctl("restart", unit)
    assert not any(name.endswith(("30-realtime.conf", "31-command-source.conf"))
                   for name in ns.show(unit, "DropInPaths")["DropInPaths"].split())


def test_crash_loop_ends_at_the_start_limit(ns: SystemdNamespace) -> None:
    unit = "u2sa@broken.service"
    ns.systemctl("start", "--no-block", unit)
    # Failed, not "activating (auto-restart)": systemd gave up after StartLimitBurst starts.
    assert wait_until(lambda: ns.state(unit) == "failed/failed", timeout=40), ns.journal_hint(unit)
    props = ns.show(unit, "NRestarts", "StartLimitBurst", "Result", "ExecMainStatus")
    assert int(props["NRestarts"]) == int(props["StartLimitBurst"]) == 5, props
    assert props["Result"] == "exit-code" and props["ExecMainStatus"] == "1", props


def test_a_recorder_of_any_name_runs_with_its_dropin_and_records(ns: SystemdNamespace,
                                                                 staged: dict[str, Any]) -> None:
    unit = f"u2sa@{RECORDER}.service"
    ns.wait_active(unit)
    props = ns.show(unit, "DropInPaths", "Nice", "IOSchedulingClass", "IOSchedulingPriority", "TimeoutStopUSec")
    assert props["DropInPaths"].split() == [f"/etc/systemd/system/{unit}.d/10-recorder.conf"], props
    # IOSchedulingClass 2 is best-effort.
    assert (props["Nice"], props["IOSchedulingClass"], props["IOSchedulingPriority"], props["TimeoutStopUSec"]) == \
        ("5", "2", "7", "15s"), props
    passwd = {line.split(":")[0]: line.split(":") for line in (staged["root"] / "etc/passwd").read_text().splitlines()}
    # It writes into the state directory, as u2sa, under ProtectSystem=strict: chunks reach the disk every second.
    assert wait_until(lambda: any(p.stat().st_size > 4096 for p in recordings(staged["root"])), timeout=20), \
        (recordings(staged["root"]), ns.journal_hint(unit))
    assert [p.stat().st_uid for p in recordings(staged["root"])] == [int(passwd["u2sa"][2])]


def test_stopping_the_target_stops_every_service_cleanly(ns: SystemdNamespace, staged: dict[str, Any]) -> None:
    pids = {name: ns.host_pid(ns.wait_active(f"u2sa@{name}.service")) for name in KINDS}
    ns.systemctl("stop", "u2sa.target", timeout=60)
    for name in KINDS:
        # PartOf= propagates the stop; systemctl waits for the target's own job only.
        assert wait_until(lambda n=name: ns.state(f"u2sa@{n}.service") == "inactive/dead", timeout=20)
        props = ns.show(f"u2sa@{name}.service", "ActiveState", "Result", "ExecMainCode", "ExecMainStatus")
        assert props["ActiveState"] == "inactive", props
        # Exited by itself with status 0 (code 1 is CLD_EXITED): not SIGTERM's default death, not a timeout's SIGKILL.
        assert props["Result"] == "success" and (props["ExecMainCode"], props["ExecMainStatus"]) == ("1", "0"), props
        assert not Path(f"/proc/{pids[name]}").exists()
    # The recorder closed its file on the way out: summary, chunk indexes, statistics that match.
    files = recordings(staged["root"])
    assert len(files) == 1, files
    with open(files[0], "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None, f"{files[0]} has no summary section"
        assert summary.chunk_indexes, f"{files[0]} has no chunk index"
        seen: set[str] = set()
        count = 0
        for _schema, channel, message in reader.iter_messages():  # through the index
            count += 1
            if channel.topic == ch.HEALTH:
                seen.add(t.Health.decode(message.data).name)
    assert count == summary.statistics.message_count > 0
    assert set(KINDS) <= seen, seen


def test_poweroff_ends_the_namespace(ns: SystemdNamespace) -> None:
    pid = ns.pid
    ns.poweroff()
    assert not ns.alive
    assert not Path(f"/proc/{pid}").exists()
    assert not ns.cgroup.exists()


def test_offline_vehicle_gets_multicast_on_lo_and_its_services_talk(tmp_path: Path) -> None:
    """No network at all (a namespace with only lo, no route): the oneshot routes multicast over lo."""
    port = private_udp_port()
    profile = write_profile(tmp_path / "vehicle.toml", port)
    root = stage_root(tmp_path / "root")
    subprocess.run([*u2sa_command(root), "install", "--vehicle", str(profile), "--root", str(root),
                    "--venv", "shared"], check=True, capture_output=True, timeout=120)
    with SystemdNamespace(root, private_network=True) as offline:
        assert offline.state("u2sa-multicast-lo.service") == "active/exited"
        assert "224.0.0.0/4 dev lo" in offline.run("ip", "-4", "route", "show").stdout
        for name in SERVICES:
            offline.wait_active(f"u2sa@{name}.service")
        found = offline.run("/opt/u2sa/venv/bin/u2sa", "services", "--vehicle", "/etc/u2sa/vehicle.toml",
                            "--json", "--timeout", "2", check=False)
        assert sorted(s["name"] for s in json.loads(found.stdout)) == sorted(SERVICES), found.stderr
        offline.systemctl("stop", "u2sa.target", "u2sa-multicast-lo.service")
        assert "224.0.0.0/4" not in offline.run("ip", "-4", "route", "show").stdout


def test_install_and_uninstall_on_a_running_system(tmp_path: Path) -> None:
    """`u2sa install` without --root, as on the vehicle: inside the namespace, whose / it installs into."""
    port = private_udp_port()
    root = stage_root(tmp_path / "root")
    (root / "opt/src").mkdir()
    good = write_profile(root / "opt/src/vehicle.toml", port)
    (root / "opt/src/bad.toml").write_text(good.read_text() + '[services.bad]\nkind = "state_estimator"\n'
                                           "settings = { sensor_timeout_s = -5.0 }\n")
    u2sa = [u2sa_inside(root)]  # the namespace has its own /tmp: a checkout there is staged in /opt
    with SystemdNamespace(root, unit="multi-user.target") as live:
        refused = live.run(*u2sa, "install", "--vehicle", "/opt/src/bad.toml", "--venv", "shared",
                           check=False, timeout=120)
        assert refused.returncode == 1 and "refusing to install" in refused.stderr, refused.stderr
        assert "sensor_timeout_s" in refused.stderr
        assert not (root / "etc/u2sa/vehicle.toml").exists()   # the check ran before anything was written
        first = live.run(*u2sa, "install", "--vehicle", "/opt/src/vehicle.toml", "--venv", "shared",
                         check=False, timeout=120)
        assert first.returncode == 0, first.stderr
        assert "created   user u2sa" in first.stdout and "daemon-reload" in first.stdout
        assert "udevadm control --reload  (udevd is not running" in first.stdout
        # The interpreter install chose (and says it chose) is one the sandboxed services can reach.
        cfg = dict(line.split(" = ", 1) for line in (root / "opt/u2sa/venv/pyvenv.cfg").read_text().splitlines()
                   if " = " in line)
        chosen = cfg["executable"]
        assert f"created   /opt/u2sa/venv  (shared venv, {chosen})" in first.stdout, first.stdout
        assert Path(chosen).is_file() and not chosen.startswith(HIDDEN_FROM_UNITS), chosen
        assert live.show("u2sa.target", "UnitFileState")["UnitFileState"] == "enabled"
        live.systemctl("start", "u2sa.target")
        for name in SERVICES:
            live.wait_active(f"u2sa@{name}.service")
        again = live.run(*u2sa, "install", "--vehicle", "/opt/src/vehicle.toml", "--venv", "shared", check=False)
        assert again.stdout.strip() == "nothing to do: everything is already installed as this profile wants"
        gone = live.run(*u2sa, "uninstall", check=False, timeout=120)
        assert gone.returncode == 0, gone.stderr
        for name in SERVICES:
            assert live.show(f"u2sa@{name}.service", "LoadState", "ActiveState") == \
                {"LoadState": "not-found", "ActiveState": "inactive"}
        assert (root / "etc/u2sa/vehicle.toml").is_file() and not (root / "etc/systemd/system/u2sa@.service").exists()
