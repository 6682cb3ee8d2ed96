"""The files a profile's services name (missions, a-priori objects, whatever else), to install beside it.

A service setting names a file when its value, a path relative to the profile's directory
(as every service resolves it, :meth:`VehicleProfile.resolve_path`), is an existing regular
file on this machine; nothing here knows which settings those are. A setting whose name ends
in ``_file`` and whose file is missing is a problem (install cannot ship it). Settings are
read where the services read them: the profile's ``settings`` and the service's config file
(which wins). Values that are device nodes or kernel files (``/dev``, ``/sys``, ``/proc``,
``/run``) or URLs are never files to copy.

Each file goes to ``/etc/u2sa`` at the same place relative to the profile as in the source
(``mission.xml`` stays ``mission.xml``), or, when it lies outside the profile's directory or
that place is taken, to ``/etc/u2sa/files/SERVICE/NAME``; the installed profile or config
then names it by that relative path, so the installed vehicle reads the installed copy.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from u2sa_hw.vehicle import VehicleProfile

ETC_DIR = "/etc/u2sa"
NOT_FILES = ("/dev/", "/sys/", "/proc/", "/run/")
FILE_SUFFIX = "_file"   # settings named so must name a file that exists


@dataclass(frozen=True)
class Reference:
    """One file a service setting names: where it is, where it goes, and the value that names it there."""

    service: str
    key: str
    in_config: bool     # the value is in the service's config file (else in the profile's settings)
    source: Path
    dest: str           # vehicle path
    value: str          # the setting's value in the installed profile or config


def _candidate(value: Any) -> str | None:
    if not isinstance(value, str):
        return None
    text = value.strip()
    if not text or "://" in text or text.startswith(NOT_FILES) or "\n" in text:
        return None
    return text


def _config_values(path: Path) -> dict[str, Any]:
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return {}   # a config that does not load is reported by the config check
    return data if isinstance(data, dict) else {}


def find_references(profile: VehicleProfile, *, taken: set[str]) -> tuple[list[Reference], list[str]]:
    """Every file the enabled services' settings name, and one problem line per ``*_file`` setting whose
    file is missing. *taken*: vehicle paths other files of the install occupy."""
    assert profile.path is not None
    base = profile.path.resolve().parent
    refs: list[Reference] = []
    problems: list[str] = []
    placed: dict[str, Path] = {}   # dest -> source, so two settings naming one file share it
    for name, spec in profile.services.items():
        if not spec.enabled:
            continue
        config = _config_values(spec.config_path) if spec.config_path.is_file() else {}
        values = [(k, v, False) for k, v in spec.settings.items() if k not in config]
        values += [(k, v, True) for k, v in config.items()]
        for key, raw, in_config in values:
            text = _candidate(raw)
            if text is None:
                continue
            path = profile.resolve_path(text)
            if path is None:
                continue
            where = spec.config_path if in_config else f"{profile.path} [services.{name}] settings"
            if not path.is_file():
                if key.endswith(FILE_SUFFIX):
                    problems.append(f"{where}: {key} = {text!r} names {path}, which is not a file; install "
                                    "cannot put it on the vehicle (fix the path or create the file)")
                continue
            source = path.resolve()
            if source in (profile.path.resolve(), spec.config_path.resolve()):
                continue
            dest, value = _place(source, base, name, placed, taken)
            placed[dest] = source
            refs.append(Reference(name, key, in_config, source, dest, value))
    return refs, problems


def _place(source: Path, base: Path, service: str, placed: Mapping[str, Path], taken: set[str]) -> tuple[str, str]:
    """The vehicle path and the profile-relative value for *source*."""
    if source.is_relative_to(base):
        rel = source.relative_to(base).as_posix()
        dest = f"{ETC_DIR}/{rel}"
        if dest not in taken and placed.get(dest, source) == source:
            return dest, rel
    rel = f"files/{service}/{source.name}"
    dest = f"{ETC_DIR}/{rel}"
    if placed.get(dest, source) != source:   # two different files of one name for one service
        stem, n = source.name, 2
        while placed.get(dest, source) != source:
            rel = f"files/{service}/{n}-{stem}"
            dest = f"{ETC_DIR}/{rel}"
            n += 1
    return dest, rel


def rewrites(refs: list[Reference], *, in_config: bool) -> dict[str, dict[str, str]]:
    """service -> {setting: installed value} for the references in configs (or in the profile's settings)."""
    out: dict[str, dict[str, str]] = {}
    for ref in refs:
        if ref.in_config == in_config:
            out.setdefault(ref.service, {})[ref.key] = ref.value
    return out
