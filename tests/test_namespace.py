"""One import name (issue 25 item 4): the drivers/, mock_devices/, hil/ and simulation/ folders
install inside ``u2sa_hw`` (setup.py's package-dir), so another project's ``drivers`` or
``simulation`` package in the same environment is left alone, and no module of ours is
importable under a second name. The wheel's contents are checked where one is built and
installed (tests/test_systemd_image.py)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FOLDERS = {"drivers": "u2sa_hw.drivers", "mock_devices": "u2sa_hw.mocks", "hil": "u2sa_hw.hil",
           "simulation": "u2sa_hw.simulation"}


def _python(code: str, *, cwd: Path, path: list[Path] | None = None) -> subprocess.CompletedProcess:
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": ":".join(map(str, path or []))}
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=120)


def test_another_projects_generic_packages_and_ours_import_side_by_side(tmp_path: Path) -> None:
    """A folder holding packages named drivers, hil, simulation and mock_devices (another project's)
    is first on the path: those names are theirs, and every package of ours still imports."""
    for name in FOLDERS:
        (tmp_path / name).mkdir()
        (tmp_path / name / "__init__.py").write_text(f"OWNER = 'another project: {name}'\n")
    code = ("import drivers, hil, simulation, mock_devices\n"
            "assert all(m.OWNER.startswith('another project') for m in (drivers, hil, simulation, mock_devices))\n"
            "import u2sa_hw.drivers.gps_nmea.driver, u2sa_hw.mocks.nmea_gps, u2sa_hw.hil.replay\n"
            "import u2sa_hw.simulation.runner\n"
            "print(u2sa_hw.drivers.__file__)\n")
    done = _python(code, cwd=tmp_path, path=[tmp_path])
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == str(REPO / "drivers" / "__init__.py")


@pytest.mark.parametrize("folder", sorted(FOLDERS))
def test_a_folder_refuses_its_top_level_name(folder: str) -> None:
    """Run from the source tree (the repo root on the path), ``import drivers`` would load a second
    copy of every module: it is refused, naming the one name to use."""
    done = _python(f"import {folder}", cwd=REPO, path=[REPO])
    assert done.returncode == 1
    assert f"ImportError: import this package as {FOLDERS[folder]}, not {folder}" in done.stderr, done.stderr
    ok = _python(f"import {FOLDERS[folder]} as m; print(m.__name__)", cwd=REPO, path=[REPO])
    assert ok.returncode == 0 and ok.stdout.strip() == FOLDERS[folder], ok.stderr


def test_setup_lists_every_package_of_the_folders() -> None:
    """Every folder of modules under the mapped folders (with an __init__.py or not yet) is a package
    the wheel carries, and no cache folder is."""
    done = subprocess.run([sys.executable, "-c", "import runpy, setuptools\n"
                           "setuptools.setup = lambda **kw: print(repr(kw))\n"
                           "runpy.run_path('setup.py')\n"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    kw = ast.literal_eval(done.stdout)
    packages = set(kw["packages"])
    for folder, name in FOLDERS.items():
        assert kw["package_dir"][name] == folder
        for module in (REPO / folder).rglob("*.py"):
            if "__pycache__" in module.parts:
                continue
            sub = module.parent.relative_to(REPO / folder).parts
            assert ".".join((name, *sub)) in packages, module
    assert not [p for p in packages if "__pycache__" in p]
