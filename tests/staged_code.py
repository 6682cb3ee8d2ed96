"""This checkout's code, staged into a test root's /opt where sandboxed units can see it.

The units run with ``PrivateTmp=`` and ``ProtectHome=``, so a checkout (or its venv) under
/tmp, /var/tmp, /root, /home or /run/user is invisible to the services that a staged
shared venv points at. :func:`stage_code` then puts, inside the staged root:

- ``/opt/u2sa-test-env/src``: the checkout (its packages, pyproject.toml, systemd/, udev/,
  docs/: what the services import and what ``u2sa install`` deploys), without .git and venvs;
- ``/opt/u2sa-test-env``: a venv on the same base interpreter whose site-packages are this
  environment's, with the editable-install path files pointing at the staged ``src``.

Files are hard links when the root is on the same filesystem (11,000 files in about a
second), copies otherwise; a path file that is rewritten is replaced, never written through
its link. Inside the namespace the root's /opt is /opt, so the staged venv's own
``sysconfig`` paths are the ones the services see: ``u2sa install`` is run from it, on the
host in a mount namespace with the root's /opt on /opt (:func:`u2sa_command`), and the
shared venv it makes points at the staged environment. A checkout outside those places is
not staged: the tests run its own ``u2sa`` as before.
"""

from __future__ import annotations

import os
import platform
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

# Where the units cannot see: PrivateTmp= (/tmp, /var/tmp) and ProtectHome= (the rest).
HIDDEN_FROM_UNITS = ("/tmp/", "/var/tmp/", "/home/", "/root/", "/run/user/")
STAGED_ENV = "/opt/u2sa-test-env"
STAGED_SRC = f"{STAGED_ENV}/src"
# Not part of what the services run or install deploys.
SKIPPED_NAMES = frozenset({".git", ".pytest_cache", ".mypy_cache", ".ruff_cache", ".tox", "sim-out"})
HOST_U2SA = Path(sys.executable).with_name("u2sa")


def checkout() -> Path:
    """The checkout whose u2sa_hw this test process imports."""
    import u2sa_hw

    return Path(u2sa_hw.__file__).resolve().parent.parent


def site_dirs() -> list[Path]:
    """This environment's site-packages (purelib, and platlib when it is another directory)."""
    paths = sysconfig.get_paths()
    return list(dict.fromkeys(Path(paths[key]).resolve() for key in ("purelib", "platlib")))


def hidden(path: Path) -> bool:
    """Whether the units' PrivateTmp=/ProtectHome= hide *path* from the services."""
    return any(f"{path}/".startswith(prefix) for prefix in HIDDEN_FROM_UNITS)


def code_hidden() -> list[Path]:
    """The checkout and site-packages directories the services could not see (empty: none)."""
    return [path for path in (checkout(), *site_dirs()) if hidden(path)]


def _same_filesystem(src: Path, dst_parent: Path) -> bool:
    return src.stat().st_dev == dst_parent.stat().st_dev


def _link_tree(src: Path, dst: Path, *, skip_venvs: bool) -> None:
    """Recreate *src* at *dst*: directories made, files hard-linked (copied across filesystems)."""
    place = os.link if _same_filesystem(src, dst.parent) else shutil.copy2
    for top, dirs, files in os.walk(src):
        rel = Path(top).relative_to(src)
        dirs[:] = [d for d in dirs if d not in SKIPPED_NAMES
                   and not (skip_venvs and (Path(top, d) / "pyvenv.cfg").exists())]
        (dst / rel).mkdir(parents=True, exist_ok=True)
        for name in files + [d for d in dirs if Path(top, d).is_symlink()]:
            source, target = Path(top, name), dst / rel / name
            if source.is_symlink():
                target.symlink_to(os.readlink(source))
            else:
                place(source, target)
        dirs[:] = [d for d in dirs if not Path(top, d).is_symlink()]


def _venv_site(env: Path) -> Path:
    return Path(sysconfig.get_path("purelib", scheme="venv", vars={"base": str(env), "platbase": str(env)}))


def _point_path_files_at(site: Path, old: Path, new: str) -> int:
    """Rewrite the path files (.pth, editable finders, egg-links) in *site* that name *old*; how many."""
    rewritten = 0
    for path in site.iterdir():
        finder = path.name.startswith("__editable__") and path.suffix == ".py"
        if not (finder or path.suffix in (".pth", ".egg-link")):
            continue
        text = path.read_text(errors="surrogateescape")
        if str(old) not in text:
            continue
        path.unlink()  # a hard link: replace the file, never write through to the environment's
        path.write_text(text.replace(str(old), new), errors="surrogateescape")
        rewritten += 1
    return rewritten


def stage_code(root: Path) -> Path:
    """Stage the checkout and a venv with this environment's site-packages into *root*/opt (see above)."""
    env = root / STAGED_ENV.lstrip("/")
    source = checkout()
    (env / "bin").mkdir(parents=True)
    _link_tree(source, root / STAGED_SRC.lstrip("/"), skip_venvs=True)
    base = Path(getattr(sys, "_base_executable", sys.executable))
    (env / "pyvenv.cfg").write_text(f"home = {base.parent}\ninclude-system-site-packages = false\n"
                                    f"version = {platform.python_version()}\n")
    (env / "bin/python").symlink_to(base)
    for alias in ("python3", f"python{sys.version_info[0]}.{sys.version_info[1]}"):
        (env / "bin" / alias).symlink_to("python")
    site = _venv_site(env)
    site.parent.mkdir(parents=True)
    purelib, *others = site_dirs()
    _link_tree(purelib, site, skip_venvs=False)
    for i, other in enumerate(others, 1):  # a platlib apart from purelib (lib64 on some systems)
        extra = site.with_name(f"site-packages-{i}")
        _link_tree(other, extra, skip_venvs=False)
        (site / f"u2sa-test-platlib-{i}.pth").write_text(f"{STAGED_ENV}/{extra.relative_to(env)}\n")
    _point_path_files_at(site, source, STAGED_SRC)
    script = env / "bin/u2sa"
    script.write_text(f"#!{STAGED_ENV}/bin/python\nimport sys\nfrom u2sa_hw.cli import main\nsys.exit(main())\n")
    script.chmod(0o755)
    return env


def is_staged(root: Path) -> bool:
    """Whether :func:`stage_code` staged code into *root*."""
    return (root / STAGED_ENV.lstrip("/") / "bin/u2sa").exists()


def u2sa_command(root: Path) -> list[str]:
    """The command that runs u2sa on the host for *root* (``install --root ROOT``): the staged
    one in a mount namespace where the root's /opt is /opt, when code was staged."""
    if not is_staged(root):
        return [str(HOST_U2SA)]
    return ["unshare", "--mount", "--propagation", "private", "sh", "-c",
            f'mount --bind "$0/opt" /opt && exec {STAGED_ENV}/bin/u2sa "$@"', str(root.resolve())]


def u2sa_inside(root: Path) -> str:
    """The u2sa to run inside the namespace booted on *root* (its /tmp and home are not the host's)."""
    return f"{STAGED_ENV}/bin/u2sa" if is_staged(root) else str(HOST_U2SA)
