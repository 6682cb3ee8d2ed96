"""How the HSM picks its restarter, and the systemd restarter's command line."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest
from conftest import wait_until

from u2sa_hw.launcher import Launcher
from u2sa_hw.services.hsm.restarters import (LauncherRestarter, NoRestarter, RestartError, SystemdRestarter,
                                             choose_restarter)
from u2sa_hw.profile.loader import load_profile


def _profile(tmp_path: Path, url: str):  # noqa: ANN202 - a VehicleProfile
    (tmp_path / "vehicle.toml").write_text(f'[vehicle]\nlcm_url = "{url}"\n[services.gps]\nkind = "state_estimator"\n')
    return load_profile(tmp_path / "vehicle.toml")


def _fake_systemctl(tmp_path: Path, *, code: int, stderr: str = "", stdout: str = "") -> Path:
    """An executable standing in for systemctl: records its arguments, answers like it."""
    script = tmp_path / "systemctl"
    script.write_text(f"#!{sys.executable}\nimport sys\n"
                      f"open({str(tmp_path / 'calls')!r}, 'a').write(' '.join(sys.argv[1:]) + '\\n')\n"
                      f"sys.stdout.write({stdout!r})\nsys.stderr.write({stderr!r})\nsys.exit({code})\n")
    script.chmod(0o755)
    return script


def test_choice_systemd_launcher_or_none(tmp_path: Path, lcm_url: str) -> None:
    profile = _profile(tmp_path, lcm_url)
    under_systemd = choose_restarter("auto", profile=profile, services=["gps"], env={"INVOCATION_ID": "abc"})
    assert isinstance(under_systemd, SystemdRestarter) and under_systemd.unit("gps") == "u2sa@gps.service"

    nothing = choose_restarter("auto", profile=profile, services=["gps"], env={"PATH": ""})
    assert isinstance(nothing, NoRestarter)
    with pytest.raises(RestartError, match="cannot restart gps: not under systemd .* no launcher answers on"):
        nothing.restart("gps", reason="test")

    launcher = Launcher(profile, output=lambda n, line: None,
                        command=lambda spec: [sys.executable, "-c", "import time; time.sleep(60)"])
    launcher.start()
    try:
        chosen = choose_restarter("auto", profile=profile, services=["gps"], env={"PATH": ""})
        assert isinstance(chosen, LauncherRestarter) and chosen.supervised() == {"gps"}
        wait_until(lambda: launcher.status()[0].state == "running", timeout=30, message="gps running")
        assert chosen.started_within("gps", 1e6) is True        # started less than 11 days ago
        assert chosen.started_within("gps", 0.0) is False       # ... but not after now
        assert chosen.started_within("imu", 1e6) is None        # not one of the launcher's
        assert "launcher restarting gps" in chosen.restart("gps", reason="test")
    finally:
        launcher.stop(timeout=10)
    with pytest.raises(RestartError, match="no launcher"):
        chosen.restart("gps", reason="test")
    assert chosen.started_within("gps", 1e6) is None            # nobody to ask
    with pytest.raises(ValueError, match="restarter = .docker. is not one of auto, systemd, launcher, none"):
        choose_restarter("docker", profile=profile, services=[])


def test_systemd_restarter_runs_systemctl_without_blocking(tmp_path: Path) -> None:
    ok = SystemdRestarter(unit_template="u2sa-{name}.service", systemctl=str(_fake_systemctl(tmp_path, code=0)))
    assert ok.restart("gps", reason="no heartbeat") == "restart of u2sa-gps.service queued with systemd"
    assert (tmp_path / "calls").read_text() == "restart --no-block u2sa-gps.service\n"

    refused = SystemdRestarter(systemctl=str(_fake_systemctl(tmp_path, code=5, stderr="Unit u2sa@gps.service not found.")))
    with pytest.raises(RestartError, match="systemctl restart u2sa@gps.service failed: Unit u2sa@gps.service not found"):
        refused.restart("gps", reason="x")
    with pytest.raises(RestartError, match="'/nonexistent/systemctl' not found"):
        SystemdRestarter(systemctl="/nonexistent/systemctl").restart("gps", reason="x")
    with pytest.raises(ValueError, match="must contain {name}"):
        SystemdRestarter(unit_template="u2sa.service")


def test_systemd_restarter_knows_a_unit_that_systemd_restarted_itself(tmp_path: Path) -> None:
    started_us = int((time.monotonic() - 5.0) * 1e6)             # the main process started 5 s ago
    running = f"ActiveState=active\nSubState=running\nExecMainStartTimestampMonotonic={started_us}\n"
    systemd = SystemdRestarter(systemctl=str(_fake_systemctl(tmp_path, code=0, stdout=running)))
    assert systemd.started_within("gps", 60.0) is True and systemd.started_within("gps", 1.0) is False
    assert (tmp_path / "calls").read_text().splitlines()[0] == \
        "show --property=ActiveState,SubState,ExecMainStartTimestampMonotonic u2sa@gps.service"
    waiting = "ActiveState=activating\nSubState=auto-restart\nExecMainStartTimestampMonotonic=0\n"
    assert SystemdRestarter(systemctl=str(_fake_systemctl(tmp_path, code=0, stdout=waiting))).started_within(
        "gps", 0.0) is True                                      # in its RestartSec: being restarted
    assert SystemdRestarter(systemctl=str(_fake_systemctl(tmp_path, code=1))).started_within("gps", 60.0) is None


class _Restarter:
    """A restarter whose supervisor says whether it restarted the service itself; records restarts."""

    kind = "test"

    def __init__(self, *, restarted_by_itself: bool | None) -> None:
        self.answer = restarted_by_itself
        self.asked: list[tuple[str, float]] = []
        self.restarted: list[str] = []

    def restart(self, service: str, *, reason: str) -> str:
        self.restarted.append(service)
        return f"restarted {service}"

    def describe(self) -> str:
        return "test"

    def started_within(self, service: str, seconds: float) -> bool | None:
        self.asked.append((service, seconds))
        return self.answer


def test_the_hsm_does_not_restart_a_service_its_supervisor_restarted_since_it_last_heard(tmp_path: Path,
                                                                                         lcm_url: str) -> None:
    from u2sa_hw import lcmtypes as t
    from u2sa_hw.services.hsm.service import HealthStatusMonitor

    profile = _profile(tmp_path, lcm_url)
    hsm = HealthStatusMonitor("hsm", profile=profile, settings={"restarter": "none"})
    try:
        beat = t.Health()
        beat.name, beat.pid, beat.status = "gps", 41, "ok"
        hsm.monitor.on_health(beat, time.monotonic() - 4.0)     # last heard from 4 s ago
        for answer, restarted in ((True, []), (False, ["gps"]), (None, ["gps"])):
            hsm.restarter = fake = _Restarter(restarted_by_itself=answer)
            ok, account = hsm.restart_unless_restarted("gps", "no heartbeat for 4.0 s")
            assert ok and fake.restarted == restarted
            assert fake.asked[0][0] == "gps" and fake.asked[0][1] == pytest.approx(4.0, abs=1.0)
        assert account == "restarted gps"
        hsm.restarter = _Restarter(restarted_by_itself=True)
        assert hsm.restart_unless_restarted("gps", "x")[1].startswith(
            "not restarting gps: it was started again since the HSM last heard from it 4.")
        hsm.restarter = fresh = _Restarter(restarted_by_itself=True)
        assert hsm.restart_unless_restarted("imu", "never heard")[0] and fresh.restarted == ["imu"]   # nothing to ask
    finally:
        hsm.transport.stop()
