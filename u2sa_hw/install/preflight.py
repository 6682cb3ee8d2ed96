"""Before ``u2sa install`` writes anything: the offline check, the devices, the referenced files.

:func:`offline_check` runs ``u2sa check``'s offline half on the profile file as written
(against the udev rules of the target: the staged root's with ``--root``), before the
profile is loaded, so a refusal lists every problem with its file, key and fix.
:func:`load_for_install` then loads the profile; it refuses, with the check's lines and
whatever ``--force`` says, a profile that does not load (every service would refuse it too)
and one with a ``[safety]`` error. :func:`preflight` reads the device
addresses into a :class:`~u2sa_hw.install.udev.DevicePlan` (past a service's wrong
setting) and finds the files the services name. Every problem is gathered first; install
then refuses with all of them, one line each, unless ``--force``. With ``--force`` the
check's errors become warnings, and what install cannot do for the vehicle (a ``/dev/u2sa``
link nothing creates, a named file that is missing) is a failure: install does the rest and
exits 1.

Each problem is said once, with one severity: the warnings are the check's lines without
their own ``error:``/``warning:`` (the CLI prints ``warning: `` before each), and what both
the check and install's own reading find (a missing named file, a link nothing creates) is
the check's line, in the refusal or as a failure, never also install's.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from u2sa_hw.profile.devices import resolve_devices
from u2sa_hw.install.referenced import MissingFile, Reference, find_references
from u2sa_hw.install.system import InstallError
from u2sa_hw.install.udev import DevicePlan, links_made, plan_devices, unmade_text
from u2sa_hw.profile.vehicle import ProfileError, VehicleProfile
from u2sa_hw.profile.loader import load_profile

RULES_DIRS = ("/etc/udev/rules.d", "/run/udev/rules.d", "/lib/udev/rules.d", "/usr/lib/udev/rules.d")
UDEV_DIRS_ENV = "U2SA_UDEV_RULES_DIRS"   # where u2sa check looks for installed rules


@dataclass
class CheckResult:
    """The offline check's findings, one line each (``error: FILE [KEY]: what; fix: ...``)."""

    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    safety_errors: list[str] = field(default_factory=list)   # the errors in [safety]: never installed
    problems: list[Any] = field(default_factory=list)        # the check's Problems (file, key...), in its order


@dataclass
class Preflight:
    """What install found before writing: the device plan, the referenced files, and the problems."""

    plan: DevicePlan
    references: list[Reference]
    warnings: list[str] = field(default_factory=list)   # said, install goes on
    failures: list[str] = field(default_factory=list)   # install cannot do these (only with --force)


def rules_dirs(root: Path) -> list[Path]:
    """The udev rules directories of the system under *root*."""
    return [root / d.lstrip("/") for d in RULES_DIRS]


@contextlib.contextmanager
def _check_sees(root: Path) -> Iterator[None]:
    """Let ``u2sa check`` look for udev rules under *root* (the staged tree), then put the variable back."""
    if root == Path("/"):
        yield
        return
    old = os.environ.get(UDEV_DIRS_ENV)
    os.environ[UDEV_DIRS_ENV] = ":".join(str(d) for d in rules_dirs(root))
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(UDEV_DIRS_ENV, None)
        else:
            os.environ[UDEV_DIRS_ENV] = old


def offline_check(profile_path: Path, *, root: Path) -> CheckResult:
    """``u2sa check``'s offline half on the file *profile_path*, as the vehicle under *root* would see it."""
    from u2sa_hw.check.offline import check_profile

    with _check_sees(root):
        problems = check_profile(profile_path)
    return CheckResult(errors=[str(p) for p in problems if p.is_error],
                       warnings=[str(p) for p in problems if not p.is_error],
                       safety_errors=[str(p) for p in problems if p.is_error and p.key.split(".")[0] == "safety"],
                       problems=list(problems))


def unlabelled(problem: Any) -> str:
    """The check's line of *problem* without its severity (``FILE [KEY]: what; fix: ...``), for a line that
    says its own (``warning: ``, ``not done: ``)."""
    return str(problem)[len(problem.severity) + 2:]


def _same_file(a: Path | str, b: Path | str) -> bool:
    return Path(a).resolve() == Path(b).resolve()


def _check_line_for(failure: str, plan_unmade: dict[str, str], checked: CheckResult) -> Any:
    """The check's error that says what install's *failure* says (a missing named file, a /dev/u2sa link
    nothing creates), or None. *plan_unmade*: install's line -> the link it is about."""
    for problem in checked.problems:
        if not problem.is_error:
            continue
        if isinstance(failure, MissingFile) and problem.key == failure.key and _same_file(problem.file, failure.file):
            return problem
        link = plan_unmade.get(failure)
        if link is not None and problem.message.startswith(f"nothing creates {link}:"):
            return problem
    return None


def refusal(path: Path, lines: list[str], *, unforceable: str = "") -> InstallError:
    """The InstallError that refuses *path* for *lines*: one line for one problem, else a list.

    *unforceable*: why ``--force`` does not go past these (empty: it does, and the text says so).
    """
    how = f"--force does not go past {'it' if len(lines) == 1 else 'them'}: {unforceable}" if unforceable \
        else "pass --force to install anyway"
    if len(lines) == 1:
        return InstallError(f"refusing to install {path}: {lines[0]} (u2sa check --vehicle {path}; {how})")
    body = "\n  ".join(lines)
    joint = "; " if unforceable else " or "
    return InstallError(f"refusing to install {path}: {len(lines)} problem(s); fix them "
                        f"(u2sa check --vehicle {path}){joint}{how}:\n  {body}")


def load_for_install(path: Path, checked: CheckResult) -> VehicleProfile:
    """The profile at *path*, once the check said it may be installed (a refusal lists every error).

    Refused whatever ``--force`` says: a profile that does not load (the services load it too
    and would refuse it at every start), and one with a ``[safety]`` error (a vehicle whose
    safety chain is mis-declared is not installed).
    """
    if checked.safety_errors:
        raise refusal(path, checked.errors, unforceable="a vehicle whose [safety] table is wrong is never installed")
    try:
        return load_profile(path)
    except ProfileError as exc:
        raise refusal(path, checked.errors or [str(exc)],
                      unforceable="the profile does not load, and every service loads it") from None


def preflight(profile: VehicleProfile, *, root: Path, taken: set[str], force: bool,
              checked: CheckResult) -> Preflight:
    """Check *profile* for installing under *root*; InstallError with every problem unless *force*.

    *checked*: :func:`offline_check` of the profile. *taken*: vehicle paths the install writes
    otherwise (a referenced file must not land on one).
    """
    from u2sa_hw.check.lenient import readable_configs

    assert profile.path is not None
    errors = checked.errors
    unreadable: list[str] = []
    try:   # a service's wrong setting (an error above) does not hide the devices of the others
        configs = readable_configs(profile)
        # the old form's services are left out: the check names the new form
        devices = resolve_devices(profile, configs=configs, skip_old_form=True).entries
        plan = plan_devices(devices, profile_path=profile.path, made_elsewhere=links_made(rules_dirs(root)))
    except (ValueError, InstallError) as exc:
        plan, unreadable = DevicePlan(), [f"no udev rules, CAN bring-up or PWM drop-ins from the devices: {exc}"]
    references, missing = find_references(profile, taken=taken)
    # What install itself cannot do for the vehicle. What the check already said (a link nothing creates, a
    # missing file) is said once, in the check's line: the refusal lists the check's errors and install's
    # own others; with --force the check's line is the "not done" one and is not also a warning.
    unmade = dict(zip(unmade_text(plan), (path for _, path in plan.unmade)))
    cannot: list[str] = []
    own: list[str] = []
    said: list[Any] = []
    for failure in [*unreadable, *unmade, *missing]:
        problem = _check_line_for(failure, unmade, checked)
        if problem is None:
            own.append(failure)
            cannot.append(failure)
        else:
            said.append(problem)
            cannot.append(unlabelled(problem))
    if (errors or own) and not force:
        raise refusal(profile.path, [*errors, *own])
    # Said as warnings (the CLI prints "warning: " before each): the check's lines without their own severity.
    gone_past = [unlabelled(p) for p in checked.problems if p not in said]
    return Preflight(plan=plan, references=references, warnings=gone_past, failures=cannot)
