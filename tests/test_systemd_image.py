"""An SD-card image as a user builds one, booted under a real systemd (tests/systemd_ns.py).

A copy of the checkout under /tmp (where a user's clone often is, and where the units'
PrivateTmp= could never see it) runs `u2sa install --vehicle FILE --root DIR` with no
--venv: the default, ``build``, makes /opt/u2sa/venv inside DIR with pip (a wheel of the
copy and its dependencies). The tests' own staging of the code (tests/staged_code.py) is
not used. The copy is then deleted, as a vehicle never has the build machine's checkout,
and systemd boots DIR: the units start and the estimator publishes its health on LCM,
importing u2sa_hw from the venv inside the image.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from staged_code import checkout  # noqa: E402
from systemd_ns import SystemdNamespace, cannot_boot_reason, stage_root, wait_until  # noqa: E402

from u2sa_hw import channels as ch  # noqa: E402
from u2sa_hw import lcmtypes as t  # noqa: E402
from u2sa_hw.bus.client import BusClient  # noqa: E402
from u2sa_hw.bus.udp_ports import private_udp_port  # noqa: E402

REASON = cannot_boot_reason()
# pip builds a venv (its own output shows how far it got): more than the suite's 120 s per test on a cold cache.
pytestmark = [pytest.mark.skipif(REASON is not None, reason=f"systemd cannot boot here: {REASON}"),
              pytest.mark.timeout(900)]

UNITS = ("u2sa.target", "u2sa@est.service", "u2sa-hsm.service")
# What a clone does not have: version control, venvs, caches, build metadata of an editable install.
NOT_IN_A_CLONE = shutil.ignore_patterns(".git", ".venv*", "__pycache__", ".pytest_cache", ".mypy_cache",
                                        ".ruff_cache", "sim-out", "bench-out", "build", "dist", "*.egg-info")


def copy_checkout(dest: Path) -> Path:
    """This checkout's files at *dest*, as a clone has them (no venv inside, found by its pyvenv.cfg)."""
    def ignore(top: str, names: list[str]) -> set[str]:
        return set(NOT_IN_A_CLONE(top, names)) | {n for n in names if (Path(top, n) / "pyvenv.cfg").is_file()}

    shutil.copytree(checkout(), dest, ignore=ignore, symlinks=True)
    return dest


def write_profile(path: Path, port: int) -> Path:
    path.write_text("\n".join([
        "[vehicle]", 'name = "image-test"', "system_id = 9", f'lcm_url = "udpm://239.255.76.67:{port}?ttl=0"', "",
        "[services.est]", 'kind = "state_estimator"', "",
        "[services.hsm]", 'kind = "hsm"', ""]))
    return path


class HealthSeen:
    """The PIDs each service's Health messages carried, from real LCM."""

    def __init__(self, url: str) -> None:
        self.client = BusClient(url)
        self.pids: dict[str, set[int]] = {}
        self.lock = threading.Lock()
        self.client.transport.subscribe(ch.HEALTH, t.Health, self._on_health)

    def _on_health(self, _channel: str, msg: Any) -> None:
        with self.lock:
            self.pids.setdefault(msg.name, set()).add(msg.pid)

    def seen(self, name: str) -> bool:
        with self.lock:
            return bool(self.pids.get(name))


def text_files_naming(directory: Path, needle: str) -> list[str]:
    """Files under *directory* (not bytecode) whose text contains *needle*."""
    found = []
    for path in directory.rglob("*"):
        if path.is_symlink() or not path.is_file() or path.suffix == ".pyc":
            continue
        if needle.encode() in path.read_bytes():
            found.append(str(path.relative_to(directory)))
    return found


def test_an_image_staged_with_the_default_venv_boots_without_the_checkout(tmp_path: Path) -> None:
    """One test, not a module fixture shared by several: under pytest-xdist each worker would build its own."""
    assert f"{tmp_path}/".startswith("/tmp/"), f"the checkout is to be copied under /tmp, not {tmp_path}"
    source = copy_checkout(tmp_path / "u2sa-hw")
    port = private_udp_port()
    profile = write_profile(tmp_path / "vehicle.toml", port)
    root = stage_root(tmp_path / "root", code=False)
    # The copy's own u2sa (its code on PYTHONPATH, run from the checkout as `.venv/bin/u2sa` would be),
    # with this environment's packages; no --venv: the default builds the venv inside the root.
    env = {**os.environ, "PYTHONPATH": str(source)}
    done = subprocess.run([sys.executable, "-m", "u2sa_hw.cli", "install", "--vehicle", str(profile),
                           "--root", str(root)], cwd=source, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "created   /opt/u2sa/venv  (build venv, " in done.stdout, done.stdout
    # pip's own progress on stderr while it builds; stdout keeps the list of changes.
    assert "u2sa install: building /opt/u2sa/venv inside " in done.stderr, done.stderr
    assert "Successfully installed" in done.stderr and "u2sa-hw-" in done.stderr, done.stderr
    assert "Successfully" not in done.stdout and "--venv shared" not in done.stderr
    venv = root / "opt/u2sa/venv"
    # Correct at /opt/u2sa/venv: no text in it names the build machine's paths (the root, the checkout).
    assert text_files_naming(venv, str(tmp_path)) == []
    assert (venv / "bin/u2sa").read_text().splitlines()[0] == "#!/opt/u2sa/venv/bin/python"
    # The project itself is installed into it, not linked to a checkout (no editable finder or u2sa path file).
    site = next(venv.glob("lib/python3.*/site-packages"))
    assert (site / "u2sa_hw/__init__.py").is_file()
    # One import name: the drivers, mocks, replay and simulation folders are inside u2sa_hw, and
    # nothing generic (drivers, hil, simulation, mock_devices) lands in site-packages.
    for inside in ("drivers/gps_nmea/driver.py", "mocks/nmea_gps.py", "hil/replay.py", "simulation/runner.py"):
        assert (site / "u2sa_hw" / inside).is_file(), inside
    top = {p.name for p in site.iterdir()}
    assert not top & {"drivers", "hil", "simulation", "mock_devices"}, sorted(top)
    assert not [p.name for p in site.iterdir() if p.name.startswith("__editable__")
                or (p.suffix == ".pth" and "u2sa" in p.name)]

    shutil.rmtree(source)   # a vehicle never has the build machine's checkout
    health = HealthSeen(f"udpm://239.255.76.67:{port}?ttl=0")
    try:
        with SystemdNamespace(root, unit="u2sa.target") as ns:
            ns.wait_active("u2sa@est.service", timeout=60)
            ns.wait_active("u2sa-hsm.service", timeout=60)
            active = ns.systemctl("is-active", *UNITS, check=False)
            assert active.stdout.split() == ["active"] * len(UNITS), (active.stdout,
                                                                       ns.journal_hint("u2sa@est.service"))
            assert wait_until(lambda: health.seen("est"), timeout=60), ns.journal_hint("u2sa@est.service")
            # What the services import is the venv's own copy, inside the image.
            where = ns.run("/opt/u2sa/venv/bin/python", "-c", "import u2sa_hw, lcm; print(u2sa_hw.__file__)")
            assert where.stdout.strip().startswith("/opt/u2sa/venv/lib/python3."), where.stdout
            assert "No module named" not in ns.journal("-u", "u2sa@est.service")
    finally:
        health.client.close()
