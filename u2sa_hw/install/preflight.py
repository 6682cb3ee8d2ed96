"""Before ``u2sa install`` writes anything: the offline check, the devices, the referenced files.

:func:`preflight` runs ``u2sa check``'s offline half on the profile (against the udev rules
of the target: the staged root's with ``--root``), reads the device addresses into a
:class:`~u2sa_hw.install.udev.DevicePlan`, and finds the files the services name. Every
problem is gathered first; install then refuses with all of them, one line each, unless
``--force``. With ``--force`` the check's errors become warnings, and what install cannot do
for the vehicle (a ``/dev/u2sa`` link nothing creates, a named file that is missing) is a
failure: install does the rest and exits 1.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from u2sa_hw.devices import profile_devices
from u2sa_hw.install.referenced import Reference, find_references
from u2sa_hw.install.system import InstallError
from u2sa_hw.install.udev import DevicePlan, links_made, plan_devices, unmade_text
from u2sa_hw.vehicle import ProfileError, VehicleProfile

RULES_DIRS = ("/etc/udev/rules.d", "/run/udev/rules.d", "/lib/udev/rules.d", "/usr/lib/udev/rules.d")
UDEV_DIRS_ENV = "U2SA_UDEV_RULES_DIRS"   # where u2sa check looks for installed rules


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


def offline_check(profile_path: Path, *, root: Path) -> tuple[list[str], list[str]]:
    """``u2sa check``'s offline half: (errors, warnings), one line each."""
    from u2sa_hw.check.offline import check_profile

    with _check_sees(root):
        problems = check_profile(profile_path)
    return [str(p) for p in problems if p.is_error], [str(p) for p in problems if not p.is_error]


def preflight(profile: VehicleProfile, *, root: Path, taken: set[str], force: bool) -> Preflight:
    """Check *profile* for installing under *root*; InstallError with every problem unless *force*.

    *taken*: vehicle paths the install writes otherwise (a referenced file must not land on one).
    """
    assert profile.path is not None
    errors, warnings = offline_check(profile.path, root=root)
    notices: list[str] = []
    unreadable: list[str] = []
    try:
        devices = profile_devices(profile, warn=notices.append)
        plan = plan_devices(devices, profile_path=profile.path, made_elsewhere=links_made(rules_dirs(root)))
    except (ProfileError, InstallError) as exc:
        plan, unreadable = DevicePlan(), [f"no udev rules, CAN bring-up or PWM drop-ins from the devices: {exc}"]
    references, missing = find_references(profile, taken=taken)
    # What install itself cannot do for the vehicle; a link the check already named is not said twice.
    cannot = [*unreadable, *unmade_text(plan), *missing]
    own = [line for (_, path), line in zip(plan.unmade, unmade_text(plan)) if not any(path in e for e in errors)]
    own += [*unreadable, *missing]
    if (errors or own) and not force:
        lines = "\n  ".join([*errors, *own])
        raise InstallError(f"refusing to install {profile.path}: {len(errors) + len(own)} problem(s); fix them "
                           f"(u2sa check --vehicle {profile.path}) or pass --force to install anyway:\n  {lines}")
    return Preflight(plan=plan, references=references, warnings=[*warnings, *notices, *errors], failures=cannot)
