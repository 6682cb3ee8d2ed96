"""The venv of ``u2sa install`` (``/opt/u2sa/venv``): where the services run from.

The venv under ``/opt/u2sa/venv`` is made one of three ways:

- ``build`` (the default): ``python -m venv`` and ``pip install`` of a wheel built from a
  copy of the checkout (so the checkout is never written), with the project's dependencies.
  With ``--root DIR`` the venv is built at ``DIR/opt/u2sa/venv`` and its absolute paths
  (the scripts' shebangs, ``activate``, ``pyvenv.cfg``) are then rewritten to
  ``/opt/u2sa/venv``, where the booted image sees it; its ``bin/python`` links to the
  interpreter by its absolute path, which the image must have (same path, same Python
  version, same architecture). Nothing in it refers to the build machine's checkout.
- ``shared``: a venv without pip whose site-packages point at the environment ``u2sa``
  runs from (a ``.pth`` file). Seconds, not minutes: for development boards and the tests'
  own staging. Its interpreter must be reachable by the user u2sa under ``ProtectHome=``
  (so not under /root or /home) and of the same Python version as the environment. With
  ``--root`` it boots only where that environment is at the same path (warned otherwise).
- ``none``: nothing; a package provides the venv.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
from collections import deque
from pathlib import Path
from typing import Callable

from u2sa_hw import __version__
from u2sa_hw.install.files import InstallTree
from u2sa_hw.install.system import InstallError, run_tool

VENV = "/opt/u2sa/venv"
VENV_MODES = ("build", "shared", "none")
HIDDEN_PREFIXES = ("/root", "/home", "/run/user")


def project_source(explicit: str | None) -> Path:
    """The project checkout (with systemd/, udev/, pyproject.toml) that install deploys."""
    candidates = [Path(explicit)] if explicit else [Path(__file__).resolve().parents[2]]
    for cand in candidates:
        if (cand / "pyproject.toml").is_file() and (cand / "systemd" / "u2sa@.service").is_file():
            return cand.resolve()
    where = explicit or candidates[0]
    raise InstallError(f"{where} is not a u2sa-hw checkout (no pyproject.toml and systemd/u2sa@.service); "
                       "run install from the source tree or pass --source DIR")


def _python_version(python: str) -> str:
    return run_tool([python, "-c", "import sys; print('%d.%d' % sys.version_info[:2])"],
                what=f"asking {python} its version").strip()


def choose_python(explicit: str | None) -> str:
    """The interpreter for the venv: *explicit*, else this one's base if the services can reach it."""
    want = f"{sys.version_info[0]}.{sys.version_info[1]}"
    if explicit:
        python = explicit
    else:
        base = str(Path(getattr(sys, "_base_executable", sys.executable)).resolve())
        system = shutil.which(f"python{want}", path="/usr/bin:/usr/local/bin")
        python = system if base.startswith(HIDDEN_PREFIXES) and system else base
    if python.startswith(HIDDEN_PREFIXES):
        raise InstallError(f"{python} lies under {', '.join(HIDDEN_PREFIXES)}, which ProtectHome= hides from the "
                           f"services; pass --python /usr/bin/python{want} (or another interpreter outside them)")
    if not Path(python).is_file():
        raise InstallError(f"--python {python}: no such interpreter")
    return python


def _source_fingerprint(source: Path) -> str:
    digest = hashlib.sha256()
    for pattern in ("pyproject.toml", "u2sa_hw/**/*.py", "drivers/**/*.py", "mock_devices/**/*.py", "hil/**/*.py"):
        for path in sorted(source.glob(pattern)):
            digest.update(str(path.relative_to(source)).encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def _run_shown(cmd: list[str], *, what: str, progress: Callable[[str], None] | None, cwd: Path) -> None:
    """Run *cmd* in *cwd*; its output line by line to *progress* as it comes (pip's own progress), or
    kept for the error message when *progress* is None."""
    if progress is None:
        run_tool(cmd, what=what, env=_venv_env(), cwd=cwd)
        return
    progress(f"{what}: {' '.join(cmd)}")
    tail: deque[str] = deque(maxlen=15)
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                          stdin=subprocess.DEVNULL, env=_venv_env(), cwd=cwd) as proc:
        assert proc.stdout is not None
        for line in proc.stdout:
            tail.append(line.rstrip())
            progress(f"  {line.rstrip()}")
    if proc.returncode != 0:
        raise InstallError(f"{what}: {' '.join(cmd)} failed ({proc.returncode}), its output is above; the last "
                           f"lines: {' | '.join(tail)}")


# Variables that would make the new venv's Python see another environment's packages.
_FOREIGN_PYTHON = ("PYTHONPATH", "PYTHONHOME", "PYTHONUSERBASE", "PYTHONSTARTUP", "VIRTUAL_ENV", "__PYVENV_LAUNCHER__")


def _venv_env() -> dict[str, str]:
    """This environment without what would make the new venv's Python see another one's packages
    (PYTHONPATH: pip would take a checkout on it, with its egg-info, for the project installed
    already; the same goes for the working directory, so pip runs in a directory of its own).
    pip's own settings (PIP_INDEX_URL, PIP_FIND_LINKS, ...) pass through."""
    return {k: v for k, v in os.environ.items() if k not in _FOREIGN_PYTHON}


# Not part of what the wheel is built from: version control, venvs, caches, build output.
_NOT_SHIPPED = shutil.ignore_patterns(".git", ".venv*", "__pycache__", "*.pyc", ".pytest_cache", ".mypy_cache",
                                      ".ruff_cache", ".tox", "build", "dist", "*.egg-info", "sim-out")


def _copy_for_wheel(source: Path, dest: Path) -> None:
    """The checkout at *dest* without what a wheel does not need (a venv inside it too, by its pyvenv.cfg)."""
    def ignore(top: str, names: list[str]) -> set[str]:
        skipped = set(_NOT_SHIPPED(top, names))
        return skipped | {n for n in names if (Path(top, n) / "pyvenv.cfg").is_file()}

    shutil.copytree(source, dest, ignore=ignore, symlinks=True)


def relocate_venv(venv: Path, target: str) -> list[str]:
    """Rewrite the venv built at *venv* to be correct at *target*: every script in bin/ (shebangs, activate)
    and pyvenv.cfg that names *venv*. The files rewritten, by name."""
    old, new = str(venv).encode(), target.encode()
    done = []
    for path in [venv / "pyvenv.cfg", *sorted((venv / "bin").iterdir())]:
        if path.is_symlink() or not path.is_file():
            continue
        data = path.read_bytes()
        if old in data:
            path.write_bytes(data.replace(old, new))
            done.append(path.name)
    return done


def _build_venv(tree: InstallTree, venv: Path, *, interpreter: str, source: Path,
                progress: Callable[[str], None] | None) -> None:
    """``python -m venv`` at *venv* and pip install of a wheel of *source* with its dependencies; made
    correct at /opt/u2sa/venv when *venv* is inside a staged root."""
    if progress is not None:
        progress(f"u2sa install: building {VENV}" + (f" inside {tree.root}" if tree.root != Path("/") else "")
                 + f" with {interpreter}: a wheel of {source}, then pip install with its dependencies")
    run_tool([interpreter, "-m", "venv", str(venv)], what="creating the venv", env=_venv_env())
    pip = [str(venv / "bin" / "python"), "-m", "pip"]
    quiet = [] if progress is not None else ["--quiet"]
    with tempfile.TemporaryDirectory(prefix="u2sa-install-") as tmp:
        copy, wheels = Path(tmp) / "src", Path(tmp) / "wheels"
        _copy_for_wheel(source, copy)
        _run_shown([*pip, "wheel", *quiet, "--no-deps", "--wheel-dir", str(wheels), str(copy)],
                   what="building the project's wheel", progress=progress, cwd=Path(tmp))
        wheel = sorted(wheels.glob("*.whl"))
        if len(wheel) != 1:
            raise InstallError(f"building the project's wheel from {source} left {len(wheel)} wheels in {wheels}")
        _run_shown([*pip, "install", *quiet, str(wheel[0])], what="pip install of the project and its dependencies",
                   progress=progress, cwd=Path(tmp))
    if tree.root != Path("/"):
        relocate_venv(venv, VENV)


def _image_interpreter_warning(root: Path, interpreter: str, version: str) -> str | None:
    """A warning when the staged *root* is a whole system (it has usr/) without *interpreter*."""
    if root == Path("/") or not (root / "usr").is_dir():
        return None
    inside = root / interpreter.lstrip("/")
    if os.path.lexists(inside):
        return None
    return (f"{VENV}/bin/python links to {interpreter} (Python {version}), which {root} does not have: the units "
            f"will not start on that image; fix: install Python {version} there at {interpreter}, or pass "
            "--python PATH of an interpreter the image has (the same path must exist here to build with)")


def _shared_outside_root(root: Path, site: str) -> str | None:
    """A warning when a shared venv staged into *root* points at an environment that is not in *root*."""
    if root == Path("/"):
        return None
    inside = root / site.lstrip("/")
    try:
        if inside.is_dir() and os.path.samefile(inside, site):
            return None
    except OSError:
        pass
    return (f"--venv shared with --root: {VENV} points at this machine's {site}, which is not in {root}; booted "
            "anywhere else every unit fails with \"No module named 'u2sa_hw'\"; fix: --venv build (the default), "
            "which builds the venv inside the root")


def ensure_venv(tree: InstallTree, *, mode: str, source: Path, python: str | None,
                progress: Callable[[str], None] | None = None) -> None:
    """Make the venv under /opt/u2sa/venv the *mode* way; nothing when it is already as wanted.

    *progress* gets a line at a time while the slow part (pip) runs; None: quiet."""
    if mode == "none":
        tree.note("skipped", VENV, "--venv none: the package provides the venv")
        return
    interpreter = choose_python(python)
    if mode == "shared":
        site = sysconfig.get_paths()["purelib"]
        if site.startswith(HIDDEN_PREFIXES):
            raise InstallError(f"--venv shared: this environment's site-packages {site} is hidden by ProtectHome=; "
                               "use --venv build")
        fingerprint = f"shared:{interpreter}:{site}"
        outside = _shared_outside_root(tree.root, site)
        if outside:
            tree.warnings.append(outside)
    else:
        fingerprint = f"build:{__version__}:{_source_fingerprint(source)}:{interpreter}"
    venv = tree.path(VENV)
    tree.ensure_parents(VENV)
    tree.new.venv = {"path": VENV, "mode": mode, "fingerprint": fingerprint}
    if tree.old.venv.get("fingerprint") == fingerprint and (venv / "bin" / "u2sa").exists():
        tree.note("unchanged", VENV, f"{mode} venv")
        return
    version = _python_version(interpreter)
    if mode == "shared" and version != f"{sys.version_info[0]}.{sys.version_info[1]}":
        raise InstallError(f"--python {interpreter} is Python {version} but this environment is "
                           f"{sys.version_info[0]}.{sys.version_info[1]}; a shared venv needs the same version")
    tree.remove_tree(VENV)
    if mode == "shared":
        run_tool([interpreter, "-m", "venv", "--without-pip", str(venv)], what="creating the venv")
        pth = venv / "lib" / f"python{version}" / "site-packages" / "u2sa-shared-env.pth"
        pth.write_text(f"import site; site.addsitedir({site!r})\n")
        script = venv / "bin" / "u2sa"
        script.write_text(f"#!{VENV}/bin/python\nimport sys\nfrom u2sa_hw.cli import main\nsys.exit(main())\n")
        script.chmod(0o755)
    else:
        warning = _image_interpreter_warning(tree.root, interpreter, version)
        if warning:
            tree.warnings.append(warning)
        _build_venv(tree, venv, interpreter=interpreter, source=source, progress=progress)
        if tree.root != Path("/"):
            tree.note("created", VENV, f"{mode} venv, {interpreter}: the image needs Python {version} there")
            return
    tree.note("created", VENV, f"{mode} venv, {interpreter}")
