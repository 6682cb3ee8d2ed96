"""A service's settings checked against what its kind declares, before anything runs.

``u2sa check`` and the profile checks call these; each problem is one line naming where
(file and table), the key, what is wrong and the fix. Nothing is started and no device is
opened: the kind's class is imported (through the service registry) only to read its fields.

- :func:`validate_settings` ``(kind, settings, *, where) -> list[str]``: the profile's
  ``settings`` of one service: the kind exists, every key is a declared field (with a
  did-you-mean), every value has the field's type, is one of its choices and within its bounds.
- :func:`validate_config_file` ``(kind, path) -> list[str]``: the same for a service's TOML
  config file (unreadable, binary or broken TOML is one problem naming the file).
- :func:`kind_problem` ``(kind, *, where) -> str | None``: an unknown kind with a did-you-mean.

The per-service combination checks (``U2SAService.check_config``) need a service instance
and run when the service starts.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, Mapping

from u2sa_hw.config.fields import ConfigError, ConfigField, coerce, to_text
from u2sa_hw.config.keys import unknown_key_problem
from u2sa_hw.registry import SERVICE_KINDS, known_kinds, resolve_kind
from u2sa_hw.service.base_config import BASE_CONFIG


def kind_problem(kind: str, *, where: str) -> str | None:
    """One line when *kind* is not a registered service kind (with a did-you-mean), else None."""
    if kind in SERVICE_KINDS:
        return None
    kinds = known_kinds()
    if kind in kinds:
        return None
    return unknown_key_problem(kind, kinds, where=where, what="service kind") + \
        "; u2sa service --list-kinds lists them"


def declared_fields(kind: str) -> dict[str, ConfigField]:
    """Every field a service of *kind* declares (the base ones included); LookupError for an unknown kind."""
    cls = resolve_kind(kind)
    return {f.name: f for f in (*BASE_CONFIG, *cls.config_fields())}


def value_problems(fields: Mapping[str, ConfigField], values: Mapping[str, Any], *, where: str) -> list[str]:
    """One line per key of *values* that is not a field of *fields*, or whose value the field refuses."""
    problems: list[str] = []
    for key, value in values.items():
        f = fields.get(key)
        if f is None:
            problems.append(unknown_key_problem(str(key), fields, where=where))
            continue
        try:
            coerce(f, value)
        except ConfigError as exc:
            default = f" (default {to_text(f.default)})" if not isinstance(f.default, list) else ""
            problems.append(f"{where}: {exc}; fix '{key}'{default}")
    return problems


def validate_settings(kind: str, settings: Mapping[str, Any], *, where: str) -> list[str]:
    """Problems of a service's profile *settings* for *kind*, one line each (``[]``: none).

    *where* names the table, e.g. ``"vehicle.toml [services.gps] settings"``.
    """
    problem = kind_problem(kind, where=where)
    if problem:
        return [problem]
    try:
        fields = declared_fields(kind)
    except ImportError as exc:
        return [f"{where}: service kind '{kind}' cannot be imported ({exc}); reinstall u2sa-hw or the package "
                "that provides it"]
    return value_problems(fields, settings, where=where)


def validate_config_file(kind: str, path: Path | str) -> list[str]:
    """Problems of service config file *path* for *kind* (``[]`` when it is fine or does not exist)."""
    path = Path(path)
    if not path.exists():
        return []
    try:
        data = tomllib.loads(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as exc:
        return [f"{path}: not a text file (byte {exc.start} is 0x{exc.object[exc.start]:02x}, not UTF-8); "
                "fix the file or delete it to use defaults"]
    except tomllib.TOMLDecodeError as exc:
        return [f"{path}: not valid TOML ({exc}); fix the file or delete it to use defaults"]
    except OSError as exc:
        return [f"{path}: cannot read ({exc.strerror or exc})"]
    return validate_settings(kind, data, where=str(path))
