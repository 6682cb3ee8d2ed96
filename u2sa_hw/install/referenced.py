"""The files a profile's services name (missions, a-priori objects, tokens, certificates), to install beside it.

Which settings name files is what each service kind declares, nothing else: a field declared
``field(..., file=True)`` (or ``file="secret"``) is a path relative to the profile's
directory (as every service resolves it, :meth:`VehicleProfile.resolve_path`), and every
such setting of an enabled service with a non-empty value names a file install copies. A
setting not declared so is never a file, whatever its value (a word that happens to be the
name of a file beside the profile stays a word). A declared file that is missing (or is not
a regular file) is a problem naming the service, the setting, the path and the fix: install
cannot put it on the vehicle. Values are read where the services read them: the service's
config file wins over the profile's ``settings``, which win over the field's default. A value
that is not a string is left to ``u2sa check`` (a type error there). A missing file's line
(:class:`MissingFile`) knows the file and key of its value, so install shows ``u2sa check``'s
line for it instead when the check named it too.

Each file goes to ``/etc/u2sa`` at the same place relative to the profile as in the source
(``mission.xml`` stays ``mission.xml``), or, when it lies outside the profile's directory or
that place is taken, to ``/etc/u2sa/files/SERVICE/NAME``; the installed profile or config
then names it by that relative path, so the installed vehicle reads the installed copy. A file
any ``file="secret"`` setting names is :attr:`Reference.secret`: install writes it root:u2sa
0640 (see :meth:`u2sa_hw.install.files.InstallTree.put_secret`).
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from u2sa_hw.profile.vehicle import ServiceSpec, VehicleProfile

ETC_DIR = "/etc/u2sa"


class MissingFile(str):
    """The problem line of a declared file that is missing, knowing the file and key its value is in (so install
    can tell when ``u2sa check`` said the same: its line is then the one shown)."""

    file: Path   # the profile or the service's config file
    key: str     # the TOML key there: services.NAME.settings.KEY in the profile, KEY in a config file

    def __new__(cls, text: str, *, file: Path, key: str) -> MissingFile:
        line = super().__new__(cls, text)
        line.file, line.key = file, key
        return line


@dataclass(frozen=True)
class Reference:
    """One file a service setting names: where it is, where it goes, and the value that names it there."""

    service: str
    key: str
    in_config: bool     # the value is in the service's config file (else the profile's settings or the default)
    source: Path
    dest: str           # vehicle path
    value: str          # the setting's value in the installed profile or config
    text: str = ""      # the setting's value as the source profile or config gives it
    secret: bool = False   # declared file="secret": installed root:u2sa 0640


def _config_values(path: Path) -> dict[str, Any]:
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return {}   # a config that does not load is reported by the config check
    return data if isinstance(data, dict) else {}


def file_fields(kind: str) -> dict[str, Any]:
    """The fields of service *kind* declared to name a file (``field(..., file=...)``), by name.

    Read through the service registry (the kind's class is imported, nothing is started);
    LookupError for an unknown kind, ImportError or AttributeError for one that does not import.
    """
    from u2sa_hw.service.validate import declared_fields

    return {name: f for name, f in declared_fields(kind).items() if f.names_file}


def _values(spec: ServiceSpec, fields: Mapping[str, Any]) -> list[tuple[str, Any, bool]]:
    """(key, value, in_config) of each declared file field of *spec*, where the service reads it."""
    config = _config_values(spec.config_path) if spec.config_path.is_file() else {}
    out = []
    for key, f in fields.items():
        if key in config:
            out.append((key, config[key], True))
        else:
            out.append((key, spec.settings.get(key, f.default), False))
    return out


def find_references(profile: VehicleProfile, *, taken: set[str]) -> tuple[list[Reference], list[str]]:
    """Every file the enabled services' declared file settings name, and one problem line per such file
    that is missing (or per service whose kind cannot be read). *taken*: vehicle paths other files of the
    install occupy."""
    assert profile.path is not None
    base = profile.path.resolve().parent
    refs: list[Reference] = []
    problems: list[str] = []
    placed: dict[str, Path] = {}   # dest -> source, so two settings naming one file share it
    for name, spec in profile.services.items():
        if not spec.enabled:
            continue
        try:
            fields = file_fields(spec.kind)
        except (LookupError, ImportError, AttributeError) as exc:
            problems.append(f"{profile.path} [services.{name}]: cannot read which files service {name} (kind "
                            f"'{spec.kind}') names ({exc}); fix the kind (u2sa check --vehicle {profile.path})")
            continue
        for key, raw, in_config in _values(spec, fields):
            if not isinstance(raw, str) or not raw.strip():
                continue   # empty: no file; not a str: u2sa check's type error
            text = raw.strip()
            path = profile.resolve_path(text)
            assert path is not None
            if not path.is_file():
                file, at = (spec.config_path, key) if in_config else (profile.path, f"services.{name}.settings.{key}")
                what = "is not a regular file" if path.exists() else "does not exist"
                problems.append(MissingFile(f"{file} [{at}]: service {name}: {key} = {text!r} names {path}, which "
                                            f"{what}: install cannot put it on the vehicle; fix: correct the path "
                                            "(relative to the profile's directory) or create the file",
                                            file=file, key=at))
                continue
            source = path.resolve()
            if source in (profile.path.resolve(), spec.config_path.resolve()):
                continue
            dest, value = _place(source, base, name, placed, taken)
            placed[dest] = source
            refs.append(Reference(name, key, in_config, source, dest, value, text=text,
                                  secret=fields[key].secret_file))
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


def installed_files(refs: list[Reference]) -> dict[str, tuple[Path, bool]]:
    """Vehicle path -> (source, secret) of every file to install; a file any secret setting names is secret."""
    out: dict[str, tuple[Path, bool]] = {}
    for ref in refs:
        source, secret = out.get(ref.dest, (ref.source, False))
        out[ref.dest] = (source, secret or ref.secret)
    return out


def rewrites(refs: list[Reference], *, in_config: bool) -> dict[str, dict[str, str]]:
    """service -> {setting: installed value} for the references in configs (or in the profile's settings)
    whose installed value differs from the one written (a default is written into the profile's settings
    only then)."""
    out: dict[str, dict[str, str]] = {}
    for ref in refs:
        if ref.in_config == in_config and ref.value != ref.text:
            out.setdefault(ref.service, {})[ref.key] = ref.value
    return out
