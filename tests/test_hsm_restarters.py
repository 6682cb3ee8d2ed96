"""How the HSM picks its restarter, and the systemd restarter's command line."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from u2sa_hw.launcher import Launcher
from u2sa_hw.services.hsm.restarters import (LauncherRestarter, NoRestarter, RestartError, SystemdRestarter,
                                             choose_restarter)
from u2sa_hw.vehicle import load_profile


def _profile(tmp_path: Path, url: str):  # noqa: ANN202 - a VehicleProfile
    (tmp_path / "vehicle.toml").write_text(f'[vehicle]\nlcm_url = "{url}"\n[services.gps]\nkind = "state_estimator"\n')
    return load_profile(tmp_path / "vehicle.toml")


def _fake_systemctl(tmp_path: Path, *, code: int, stderr: str = "") -> Path:
    """An executable standing in for systemctl: records its arguments, answers like it."""
    script = tmp_path / "systemctl"
    script.write_text(f"#!{sys.executable}\nimport sys\n"
                      f"open({str(tmp_path / 'calls')!r}, 'a').write(' '.join(sys.argv[1:]) + '\\n')\n"
                      f"sys.stderr.write({stderr!r})\nsys.exit({code})\n")
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
        assert "launcher restarting gps" in chosen.restart("gps", reason="test")
    finally:
        launcher.stop(timeout=10)
    with pytest.raises(RestartError, match="no launcher"):
        chosen.restart("gps", reason="test")
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
