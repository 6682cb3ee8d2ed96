"""The ``[services.NAME]`` tables of a profile, checked against what each service kind declares.

For each service: its table's keys, its ``kind`` (a registered kind, with a did-you-mean),
every value of its ``settings`` and of its config file against the kind's declared fields
(unknown names, type, choices, non-finite numbers), the whole config through the kind's own
validation (ranges and combinations the kind checks before it starts), the files its
config names (the fields the kind declares ``file=...``: present, and a mission or object
list readable as the service reads it), and its ``supervision`` table against the HSM's rules.
"""

from __future__ import annotations

import logging
import math
import tomllib
from pathlib import Path
from typing import Any, Mapping

from u2sa_hw.check.problem import Collector, did_you_mean, type_name
from u2sa_hw.profile.loader import SERVICE_KEYS

_TYPES: dict[str, type] = {"settings": dict, "enabled": bool, "required": bool, "supervision": dict}
SERVICE_KEY_TYPES: dict[str, type | tuple[type, ...]] = {   # the loader's keys, with the type each takes
    name: _TYPES.get(name, str) for name in SERVICE_KEYS}
_quiet = logging.getLogger("u2sa_hw.check")
_quiet.addHandler(logging.NullHandler())
_quiet.propagate = False


def check_services(path: Path, data: Mapping[str, Any], services: Mapping[str, Any], out: Collector, *,
                   profile: Any) -> None:
    """Add every problem of every ``[services.NAME]`` table of the profile at *path* to *out*."""
    from u2sa_hw.registry import known_kinds

    kinds = known_kinds()
    base = path.resolve().parent
    vehicle = data.get("vehicle") if isinstance(data.get("vehicle"), dict) else {}
    config_dir = vehicle.get("config_dir", "config")
    config_dir = base / (config_dir if isinstance(config_dir, str) else "config")
    for name, table in services.items():
        key = f"services.{name}"
        if not isinstance(table, dict):
            out.error(key, f"must be a table, got {type_name(table)}", f"write [services.{name}] with kind = \"...\"")
            continue
        for k, value in table.items():
            want = SERVICE_KEY_TYPES.get(k)
            if want is None:
                setting_names = _setting_names(table.get("kind"))
                hint = did_you_mean(k, SERVICE_KEYS) or did_you_mean(k, setting_names)
                out.error(f"{key}.{k}", f"unknown key '{k}'{hint}",
                          f"a service table has {', '.join(SERVICE_KEYS)}; a setting goes in settings = {{ ... }}")
            elif not isinstance(value, want):
                names = want.__name__ if isinstance(want, type) else " or ".join(w.__name__ for w in want)
                out.error(f"{key}.{k}", f"must be {names}, got {type_name(value)} {value!r}",
                          "see the example profiles in examples/")
        kind = table.get("kind")
        if kind is None:
            out.error(f"{key}.kind", "missing 'kind' (what the service is)",
                      "add kind = \"...\" (u2sa service --list-kinds lists them)")
            continue
        if not isinstance(kind, str):
            continue
        if kind not in kinds:   # a disabled service is not started: its unknown kind is only a warning
            report = out.error if table.get("enabled", True) is not False else out.warning
            report(f"{key}.kind", f"unknown service kind '{kind}'{did_you_mean(kind, kinds)}",
                   f"use one of {', '.join(sorted(kinds))}")
            continue
        cls = _service_class(kind, key, out)
        if cls is None:
            continue
        config = table.get("config")
        config_path = base / config if isinstance(config, str) else config_dir / f"{name}.toml"
        if table.get("enabled", True) is False:
            continue   # a disabled service is not started: its values are checked when it is enabled
        _check_config(name, cls, table.get("settings", {}), config_path, explicit=isinstance(config, str),
                      profile=profile, base=base, out=out)
        _check_supervision(name, table.get("supervision"), out)


def _setting_names(kind: Any) -> list[str]:
    """The setting names of *kind* (for a did-you-mean), [] for an unknown kind."""
    from u2sa_hw.registry import known_kinds, resolve_kind

    if not isinstance(kind, str) or kind not in known_kinds():
        return []
    try:
        return list(_fields(resolve_kind(kind)))
    except (ImportError, AttributeError):
        return []


def _service_class(kind: str, key: str, out: Collector) -> Any:
    from u2sa_hw.registry import resolve_kind

    try:
        return resolve_kind(kind)
    except ImportError as exc:
        out.error(f"{key}.kind", f"kind '{kind}' cannot be imported ({exc})",
                  "install the package that provides it (pip install -e .) or fix the entry point")
    except AttributeError as exc:
        out.error(f"{key}.kind", f"kind '{kind}' is registered but its class is missing ({exc})",
                  "fix the registry entry in u2sa_hw/registry.py or the entry point")
    return None


def _fields(cls: Any) -> dict[str, Any]:
    from u2sa_hw.service.base_config import BASE_CONFIG

    return {f.name: f for f in (*BASE_CONFIG, *cls.config_fields())}


def _device_of(service: str, *tables: Mapping[str, Any]) -> str:
    """The device a service names (``device`` in the last of *tables* that sets it), else its name."""
    named = [t["device"] for t in tables if isinstance(t.get("device"), str) and t["device"].strip()]
    return named[-1].strip() if named else service


def _check_values(values: Mapping[str, Any], fields: Mapping[str, Any], out: Collector, *, key: str,
                  file: Path | None, unknown_is_error: bool, device: str) -> bool:
    """Names and types of *values*; True when every value can be used. A driver's (a kind with a ``device``
    setting) old-form address setting is an error naming *device* and the new form."""
    from u2sa_hw.config.fields import ConfigError, coerce, to_text
    from u2sa_hw.config.keys import old_form_fix, old_form_keys

    usable = True
    old = old_form_keys(values, fields)
    for name, value in values.items():
        at = f"{key}.{name}" if key else name
        f = fields.get(name)
        if name in old:
            out.error(at, f"'{name}' is the old form", str(old_form_fix(name, device=device)), file=file)
            usable = False
            continue
        if f is None:
            text = f"'{name}' is not a setting of this service{did_you_mean(name, fields)}"
            fix = f"its settings: {', '.join(sorted(fields))}"
            (out.error if unknown_is_error else out.warning)(at, text, fix, file=file)
            continue
        try:
            coerced = coerce(f, value)
        except ConfigError as exc:
            hint = ""
            if f.choices and isinstance(value, str):   # a case-insensitive field's choices compare in lower case
                fold = str.lower if getattr(f, "case_insensitive", False) else str
                hint = did_you_mean(fold(value), [fold(str(c)) for c in f.choices])
            out.error(at, _reason(str(exc), name) + hint, _value_fix(f, value), file=file)
            usable = False
            continue
        if isinstance(coerced, float) and not math.isfinite(coerced) and not getattr(f, "allow_nonfinite", False):
            out.error(at, f"{coerced} is not a finite number", f"give a finite value like {to_text(f.default)}",
                      file=file)
            usable = False
    return usable


def _reason(text: str, name: str) -> str:
    """A ConfigError's text without the field name the problem's key already gives."""
    for prefix in (f"field '{name}' ", f"config field '{name}' "):
        if text.startswith(prefix):
            return text[len(prefix):]
    return text


def _value_fix(f: Any, value: Any) -> str:
    """What to write instead of *value* for field *f*: its type, choices or range."""
    from u2sa_hw.config.fields import choices_text, to_text

    if f.choices:
        return f"use one of {choices_text(f)}"
    if getattr(f, "names_file", False) and not isinstance(value, str):
        return f"write the file's path as a string, relative to the profile's directory: {f.name} = \"FILE\""
    if type(value) is not f.type and not (f.type is float and type(value) is int):
        article = "an" if f.type_name[0] in "aeiou" else "a"
        return f"write {article} {f.type_name} like {f.name} = {to_text(f.default)}"
    range_text = f.range_text() if hasattr(f, "range_text") else ""
    return f"give a value {range_text} (default {to_text(f.default)})" if range_text else \
        f"give a value like {to_text(f.default)}"


def _read_config_file(path: Path, key: str, out: Collector) -> dict[str, Any] | None:
    try:
        raw = path.read_bytes()
    except OSError as exc:
        out.error(key, f"cannot read this service's config file {path} ({exc.strerror or exc})",
                  "fix its permissions", file=path)
        return None
    try:
        return tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        out.error("", f"not UTF-8 text (byte {raw[exc.start]:#04x} at offset {exc.start})",
                  "rewrite the file as UTF-8 TOML, or delete it to use the defaults", file=path)
    except tomllib.TOMLDecodeError as exc:
        out.error("", f"not valid TOML: {exc}", "fix the syntax at that line, or delete the file to use the defaults",
                  file=path)
    return None


def _check_config(name: str, cls: Any, settings: Any, config_path: Path, *, explicit: bool, profile: Any,
                  base: Path, out: Collector) -> None:
    key = f"services.{name}"
    fields = _fields(cls)
    usable = True
    if isinstance(settings, dict):
        usable = _check_values(settings, fields, out, key=f"{key}.settings", file=None, unknown_is_error=True,
                               device=_device_of(name, settings))
    else:
        settings, usable = {}, False
    file_values: dict[str, Any] = {}
    if config_path.exists():
        read = _read_config_file(config_path, key, out)
        if read is None:
            usable = False
        else:
            file_values = read
            usable = _check_values(read, fields, out, key="", file=config_path, unknown_is_error=False,
                                   device=_device_of(name, settings, read)) and usable
    elif explicit:
        out.warning(f"{key}.config", f"config file {config_path} does not exist: the service runs with its "
                    "defaults and the profile's settings", "correct the path, or create the file")
    if not usable:
        return   # the kind's own checks would only repeat the errors above
    effective = {n: f.default for n, f in fields.items()}
    effective.update({k: v for k, v in settings.items() if k in fields})
    effective.update({k: v for k, v in file_values.items() if k in fields})
    _check_semantics(name, cls, effective, config_path, fields, profile=profile, out=out)
    in_file = {k for k in file_values if k in fields}
    _check_files(name, effective, fields, base=base, profile=profile, out=out, config_path=config_path,
                 in_file=in_file, in_settings={k for k in settings if k in fields})


def _check_semantics(name: str, cls: Any, values: dict[str, Any], config_path: Path, fields: Mapping[str, Any], *,
                     profile: Any, out: Collector) -> None:
    """The kind's own validation (combinations, what one field cannot say) of the whole effective config.

    The per-value rules (type, choices, bounds) were checked above through config.coerce;
    this runs the kind's ``check_config`` hook, as a start would, on an instance that has only
    its name, config, logger and profile (nothing opened, no bus, no device link: the device
    addresses are checked with the devices). A hook that needs more than that cannot run here:
    that is a warning line naming the kind and why, never a silent pass.
    """
    from u2sa_hw.config.configurator import Configurator
    from u2sa_hw.config.fields import ConfigError

    key = f"services.{name}.settings"
    config = Configurator(None, fields.values(), logger=_quiet, initial=values)
    service = cls.__new__(cls)   # the kind's checks read only its name and config; nothing is opened
    service.name, service.config, service.logger = name, config, _quiet
    if profile is not None:
        service.profile = profile
    try:
        service.check_config()
    except (ConfigError, ValueError) as exc:
        reason = str(exc)
        text = reason.split(": ", 1)[1] if reason.startswith(("service '", f"{name}: ")) else reason
        out.error(key, text, "change the value in the profile's settings or the service's config file "
                  f"{config_path}")
    except Exception as exc:  # noqa: BLE001 - a kind's hook that needs a running service must not end the check
        out.warning(f"services.{name}", f"the checks of kind {cls.__name__} (check_config) could not run offline "
                    f"({type(exc).__name__}: {exc}); they run only when the service starts",
                    "start the service once to see them, and report this: a kind's check_config should read only "
                    "its name, config and profile")


def _check_files(name: str, values: Mapping[str, Any], fields: Mapping[str, Any], *, base: Path, profile: Any,
                 out: Collector, config_path: Path, in_file: set[str], in_settings: set[str]) -> None:
    """Every setting the kind declares a file (``field(..., file=...)``) names a file that exists and reads as
    the service reads it; the problem is on the file and key the value is in (config file, profile, default)."""
    for field_name, f in fields.items():
        if not getattr(f, "names_file", False):
            continue
        text = values.get(field_name)
        if not isinstance(text, str) or not text.strip():
            continue   # empty: no file; another type: the type error above
        path = Path(text.strip()).expanduser()
        path = path if path.is_absolute() else base / path   # as VehicleProfile.resolve_path
        if field_name in in_file:
            key, file, where = field_name, config_path, f"in {config_path.name}"
        elif field_name in in_settings:
            key, file, where = f"services.{name}.settings.{field_name}", None, "in the profile's settings"
        else:
            key, file, where = f"services.{name}.settings.{field_name}", None, "by default"
        if not path.is_file():
            what = "is not a regular file" if path.exists() else "does not exist"
            out.error(key, f"file {path} {what} ({field_name} = {text.strip()!r} {where})",
                      "correct the path (relative to the profile's directory) or add the file", file=file)
            continue
        problem, severity = _read_referenced(field_name, path, profile, secret=f.secret_file)
        if problem:
            report = out.error if severity == "error" else out.warning
            report("", problem, f"fix the file named by services.{name} {field_name}", file=path)


def _read_referenced(field_name: str, path: Path, profile: Any, *, secret: bool) -> tuple[str | None, str]:
    """Why the service could not read *path* and how bad that is, or (None, ""); missions and object lists
    are parsed. A secret file this user may not read (installed root:u2sa 0640, and the check run by someone
    outside the group u2sa) is a warning: the services read it as u2sa."""
    try:
        if field_name == "mission_file":
            from u2sa_hw.services.mission.xml import load_mission

            load_mission(path)
        elif field_name == "objects_file":
            from u2sa_hw.services.world.xml import load_objects
            from u2sa_hw.profile.vehicle import Origin

            load_objects(path, origin=profile.origin if profile is not None else Origin())
        else:
            path.read_bytes()
    except PermissionError as exc:
        if secret:
            return (f"a secret this user cannot read ({exc.strerror}); the services read it as user u2sa: run "
                    "u2sa check as root or a member of the group u2sa to check it", "warning")
        return str(exc).replace(f"{path}: ", ""), "error"
    except (OSError, ValueError) as exc:
        return str(exc).replace(f"{path}: ", ""), "error"
    return None, ""


def _check_supervision(name: str, table: Any, out: Collector) -> None:
    """The ``[services.NAME.supervision]`` keys and types, as the HSM reads them."""
    from u2sa_hw.channels import BASE_TYPES
    from u2sa_hw.services.hsm.rules import _KEYS, _checked
    from u2sa_hw.profile.vehicle import ProfileError

    if table is None or not isinstance(table, dict):
        return
    key = f"services.{name}.supervision"
    for k, value in table.items():
        f = _KEYS.get(k)
        if f is None:
            out.error(f"{key}.{k}", f"unknown key '{k}'{did_you_mean(k, _KEYS)}", f"known: {', '.join(sorted(_KEYS))}")
            continue
        try:
            _checked(key, k, value, f.default)
        except ProfileError as exc:
            out.from_text(str(exc), key=f"{key}.{k}", fix="see docs/supervision.md")
    channel = table.get("data_channel")
    if isinstance(channel, str) and channel and channel not in BASE_TYPES:
        hint = did_you_mean(channel, BASE_TYPES)
        out.error(f"{key}.data_channel", f"'{channel}' is not a channel of the system{hint}",
                  "name the channel the service publishes its data on (docs/supervision.md)")
    stale = table.get("stale_after_s", 0)
    if isinstance(stale, (int, float)) and stale > 0 and not table.get("data_channel"):
        out.error(f"{key}.stale_after_s", "stale_after_s needs data_channel",
                  "add data_channel = \"...\" (the channel the service's data goes out on), or remove stale_after_s")
