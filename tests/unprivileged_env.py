"""An interpreter the user nobody can run, with this checkout's code, for the permission tests.

Root ignores file modes, so a test of a permission runs its child as the user nobody
(``conftest.unprivileged``). That child needs this environment's interpreter, its standard
library, its site-packages and the checkout, all readable by nobody. From a checkout in a
directory other users cannot enter (``mktemp -d``, /root, a home of mode 0700 or 0750), or
with a pyenv Python under a 0700 /root, some of them are not. :func:`python_for_nobody` then
stages them, once per test process and only when a test asks, in a 0755 directory in the
temporary directory (as :mod:`staged_code` stages the code for the systemd tests):

- ``src``: the checkout (its packages and data), without .git and venvs;
- ``python``: the base interpreter (its binary, libpython and standard library), only when
  nobody cannot run it where it is;
- ``venv``: a venv on that interpreter whose site-packages are this environment's, with the
  editable install's path files pointing at ``src``.

Files are hard links where the stage is on the sources' filesystem (some 15,000 in about a
second), copies otherwise or where a file is not readable by others (a clone made with umask
077). When nobody can already run ``sys.executable`` with this checkout's ``u2sa_hw`` (a
checkout under a 0755 directory), nothing is staged. :func:`remove_stage` removes the stage at the
end of the session; one left by a killed test process is removed by the next that stages.
"""

from __future__ import annotations

import functools
import os
import platform
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path
from typing import Callable

from staged_code import SKIPPED_NAMES, checkout, site_dirs

STAGE_PREFIX = "u2sa-nobody-"   # then the staging process's id
NOBODY = ("--reuid=65534", "--regid=65534", "--clear-groups")
# What nobody's child prints: the interpreter it runs, and where its u2sa_hw comes from.
PROBE = "import sys, u2sa_hw; print(sys.version); print(sys.base_prefix); print(u2sa_hw.__file__)"
BASE_PROBE = "import sys; print(sys.version); print(sys.base_prefix)"
# Not what a child imports or reads: the checkout's outputs (and what staged_code leaves out).
SRC_SKIPPED = SKIPPED_NAMES | {"bench-out", ".u2sa"}
# Parts of the standard library no child of a test imports (the base's own packages are not the venv's).
STDLIB_SKIPPED = frozenset({"site-packages", "dist-packages", "test", "idlelib", "turtledemo", "ensurepip"})

_stage: Path | None = None
stage_seconds: float | None = None   # how long staging took in this process (None: nothing staged)


class StageError(RuntimeError):
    """The staged interpreter does not run as nobody either."""


def as_nobody() -> list[str]:
    """setpriv to the user and group nobody, without supplementary groups (empty: no setpriv)."""
    setpriv = shutil.which("setpriv")
    return [] if setpriv is None else [setpriv, *NOBODY]


def _seen_by_nobody(python: list[str], env: dict[str, str] | None = None, code: str = PROBE) -> list[str]:
    """What *code* (:data:`PROBE`) prints when *python* runs it as nobody, from /, without $PYTHONPATH."""
    clean = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    done = subprocess.run([*as_nobody(), *python, "-c", code], capture_output=True, text=True, timeout=60,
                          cwd="/", env={**clean, **(env or {})})
    return done.stdout.splitlines() if done.returncode == 0 else [done.stderr.strip()]


def _ours() -> str:
    import u2sa_hw

    return str(Path(u2sa_hw.__file__).resolve())


def _stage_parent(source: Path) -> str:
    """A temporary directory on *source*'s filesystem, where one is (hard links), else the default one."""
    default = tempfile.gettempdir()
    for parent in (default, "/var/tmp"):
        if os.path.isdir(parent) and os.stat(parent).st_dev == source.stat().st_dev:
            return parent
    return default


def _place(source: str, target: str, mode: int) -> None:
    """*target* as *source* (of *mode*) for everyone: a hard link when others may read it, else a readable copy."""
    if mode & 0o004:
        try:
            os.link(source, target)
            return
        except OSError:   # another filesystem (EXDEV), or links refused
            pass
    shutil.copy2(source, target)
    os.chmod(target, (mode & 0o777) | 0o444 | (0o111 if mode & 0o100 else 0))


def _place_tree(source: Path, target: Path, skip: Callable[[os.DirEntry], bool] = lambda entry: False) -> None:
    """Recreate *source* at *target*: directories 0755, files placed, symlinks as they are, *skip* left out."""
    os.mkdir(target)
    with os.scandir(source) as entries:
        for entry in entries:
            if skip(entry):
                continue
            dst = os.path.join(target, entry.name)
            if entry.is_symlink():
                os.symlink(os.readlink(entry.path), dst)
            elif entry.is_dir():
                _place_tree(Path(entry.path), Path(dst), skip)
            else:
                _place(entry.path, dst, entry.stat().st_mode)


def _stage_interpreter(home: Path) -> tuple[Path, dict[str, str]]:
    """The base interpreter staged at *home*: its binary, and the environment it needs there."""
    base = Path(sys.base_prefix)
    exe = Path(os.path.realpath(getattr(sys, "_base_executable", sys.executable)))
    (home / "bin").mkdir(parents=True)
    _place(str(exe), str(home / "bin" / exe.name), exe.stat().st_mode)
    prefixes = {name: str(base) for name in ("base", "platbase", "installed_base", "installed_platbase")}
    for key in ("stdlib", "platstdlib"):   # where Python looks for them: the same path below its prefix
        lib = Path(sysconfig.get_path(key, vars=prefixes))
        staged = home / lib.relative_to(base)
        if not staged.exists():
            staged.parent.mkdir(parents=True, exist_ok=True)
            _place_tree(lib, staged, skip=lambda entry, top=str(lib): entry.name in STDLIB_SKIPPED
                        and os.path.dirname(entry.path) == top)
    env: dict[str, str] = {}
    if sysconfig.get_config_var("Py_ENABLE_SHARED"):   # libpython, which the binary finds by an absolute RUNPATH
        libdir = Path(sysconfig.get_config_var("LIBDIR"))
        staged_libdir = home / (libdir.relative_to(base) if libdir.is_relative_to(base) else "lib")
        staged_libdir.mkdir(parents=True, exist_ok=True)
        for name in {sysconfig.get_config_var("INSTSONAME"), sysconfig.get_config_var("LDLIBRARY")} - {None}:
            if (libdir / name).exists() and not (staged_libdir / name).exists():
                _place(str(libdir / name), str(staged_libdir / name), (libdir / name).stat().st_mode)
        env["LD_LIBRARY_PATH"] = str(staged_libdir)
    return home / "bin" / exe.name, env


def _point_path_files_at(site: Path, old: Path, new: Path) -> None:
    """Rewrite the path files (.pth, editable finders, egg-links) in *site* that name *old*."""
    for path in site.iterdir():
        finder = path.name.startswith("__editable__") and path.suffix == ".py"
        if not (finder or path.suffix in (".pth", ".egg-link")):
            continue
        text = path.read_text(errors="surrogateescape")
        if str(old) in text:
            path.unlink()   # perhaps a hard link: replace the file, never write through to the environment's
            path.write_text(text.replace(str(old), str(new)), errors="surrogateescape")


def _stage_venv(stage: Path) -> list[str]:
    """Stage the checkout, the interpreter if need be, and a venv on it; the command that runs it."""
    source = checkout()
    _place_tree(source, stage / "src", skip=lambda entry: entry.name in SRC_SKIPPED
                or entry.is_dir(follow_symlinks=False) and os.path.exists(os.path.join(entry.path, "pyvenv.cfg")))
    base = Path(getattr(sys, "_base_executable", sys.executable))
    env: dict[str, str] = {}
    if _seen_by_nobody([str(base), "-I"], code=BASE_PROBE) != [sys.version, sys.base_prefix]:
        base, env = _stage_interpreter(stage / "python")
    venv = stage / "venv"
    (venv / "bin").mkdir(parents=True)
    (venv / "pyvenv.cfg").write_text(f"home = {base.parent}\ninclude-system-site-packages = false\n"
                                     f"version = {platform.python_version()}\n")
    (venv / "bin/python").symlink_to(base)
    site = Path(sysconfig.get_path("purelib", scheme="venv", vars={"base": str(venv), "platbase": str(venv)}))
    purelib, *others = site_dirs()
    site.parent.mkdir(parents=True, exist_ok=True)
    _place_tree(purelib, site)
    for i, other in enumerate(others, 1):   # a platlib apart from purelib (lib64 on some systems)
        extra = site.with_name(f"site-packages-{i}")
        _place_tree(other, extra)
        (site / f"u2sa-test-platlib-{i}.pth").write_text(f"{extra}\n")
    _point_path_files_at(site, source, stage / "src")
    prefix = ["env", *(f"{k}={v}" for k, v in env.items())] if env else []
    return [*prefix, str(venv / "bin/python")]


def _remove_abandoned(parent: str) -> None:
    """Remove the stages of test processes that are gone (killed before :func:`remove_stage`)."""
    for path in Path(parent).glob(f"{STAGE_PREFIX}*-*"):
        pid = path.name[len(STAGE_PREFIX):].split("-")[0]
        if pid.isdigit() and not Path(f"/proc/{pid}").exists():
            shutil.rmtree(path, ignore_errors=True)


@functools.cache
def python_for_nobody() -> tuple[str, ...]:
    """The command that runs this environment's Python, with this checkout's u2sa_hw, as nobody.

    ``sys.executable`` when nobody can run it as it is; else a staged one (see above), staged
    on the first call. Raises :class:`StageError` when nobody cannot run that one either.
    """
    global _stage, stage_seconds
    if _seen_by_nobody([sys.executable]) == [sys.version, sys.base_prefix, _ours()]:
        return (sys.executable,)
    start = time.monotonic()
    parent = _stage_parent(checkout())
    _remove_abandoned(parent)
    _stage = Path(tempfile.mkdtemp(prefix=f"{STAGE_PREFIX}{os.getpid()}-", dir=parent))
    _stage.chmod(0o755)
    umask = os.umask(0o022)   # what staging makes, everyone may read (a copy also gets o+r: _place)
    try:
        command = _stage_venv(_stage)
        stage_seconds = time.monotonic() - start
        seen = _seen_by_nobody(command[-1:], dict(arg.split("=", 1) for arg in command[1:-1]))
        expected = str(_stage / "src" / Path(_ours()).relative_to(checkout()))
        if len(seen) != 3 or seen[0] != sys.version or seen[2] != expected:
            raise StageError(f"the user nobody cannot run the Python staged in {_stage} either: {seen}")
    except BaseException:
        remove_stage()
        raise
    finally:
        os.umask(umask)
    return tuple(command)


def remove_stage() -> None:
    """Remove what :func:`python_for_nobody` staged, if anything."""
    global _stage
    if _stage is not None:
        shutil.rmtree(_stage, ignore_errors=True)
        _stage = None
