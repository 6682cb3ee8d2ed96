"""Configurator (requirement C1, C7): a per-service TOML file of typed variables.

A service declares its fields with defaults (the default's type is the field's type:
int, float, bool or str) and, where only some values make sense, the allowed ``choices``.
A missing file means defaults; the file is created, with every field, on the first change.
A change is checked against the declared type; a wrong type is refused with a message
naming the field, the expected and the given type (a value outside ``choices``: the field
and the allowed values). Writes are atomic (temp file in the same directory, fsync, rename),
so a crash or a full disk never leaves a half-written file; an unwritable file makes ``set``
return False and logs why.

Text (what ``u2sa param set`` sends) is read as a TOML literal: ``42``, ``2.5``, ``true``,
``"text"``. For a string field a TOML string literal (``"passthrough"`` or ``'passthrough'``)
gives its contents, and any other text (a bare word, ``42``) is taken as it is.
"""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
import threading
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import tomli_w

TYPE_NAMES = {int: "int", float: "float", bool: "bool", str: "str"}


class ConfigError(ValueError):
    """A config file or value is invalid; the message names the file/field and the fix."""


@dataclass(frozen=True)
class ConfigField:
    """One declared variable: its name, default (whose type is the field's type) and help."""

    name: str
    default: Any
    help: str = ""
    choices: tuple[Any, ...] = ()

    @property
    def type(self) -> type:
        """The Python type of the field."""
        return type(self.default)

    @property
    def type_name(self) -> str:
        """``int``, ``float``, ``bool`` or ``str``."""
        return TYPE_NAMES.get(self.type, self.type.__name__)


def field(name: str, default: Any, help: str = "", *,  # noqa: A002 - reads well at call sites
          choices: Iterable[Any] = ()) -> ConfigField:
    """Declare a config variable (shorthand for :class:`ConfigField`); *choices*: the only values allowed."""
    if type(default) not in TYPE_NAMES and not isinstance(default, list):
        raise TypeError(f"config field {name}: default must be int, float, bool, str or list, not {type(default).__name__}")
    allowed = tuple(choices)
    if allowed and default not in allowed:
        raise ValueError(f"config field {name}: default {default!r} is not one of its choices {allowed!r}")
    return ConfigField(name, default, help, allowed)


def choices_text(f: ConfigField) -> str:
    """The allowed values of *f* as TOML literals, comma separated."""
    return ", ".join(to_text(c) for c in f.choices)


def coerce(f: ConfigField, value: Any) -> Any:
    """*value* as *f*'s type, or ConfigError naming the field, the expected and the given type.

    An int is accepted for a float field; nothing else is converted (a bool is not an int).
    """
    expected = f.type
    given = type(value)
    if given is expected:
        result = value
    elif expected is float and given is int:
        result = float(value)
    else:
        raise ConfigError(f"field '{f.name}' expects {f.type_name}, got {TYPE_NAMES.get(given, given.__name__)} "
                          f"{value!r}")
    if f.choices and result not in f.choices:
        raise ConfigError(f"field '{f.name}' must be one of {choices_text(f)}; got {to_text(result)}")
    return result


def parse_text(f: ConfigField, text: str) -> Any:
    """Parse *text* as *f*'s value: a TOML literal, or for a str field also any other text as it is.

    For a str field, a TOML string literal (``"passthrough"``, ``'passthrough'``) gives its
    contents, so the quoted form ``u2sa param get`` prints can be fed back to ``set``.
    """
    try:
        table = tomllib.loads(f"v = {text}")
        if len(table) != 1:  # "1\nother = 2" is not one literal
            raise tomllib.TOMLDecodeError("more than one value")
        value = table["v"]
    except tomllib.TOMLDecodeError:
        if f.type is str:
            return coerce(f, text)
        raise ConfigError(f"field '{f.name}' expects {f.type_name}, got unparseable text {text!r}") from None
    if f.type is str and not isinstance(value, str):
        return coerce(f, text)  # `name = 42` for a string field means the string "42"
    return coerce(f, value)


def to_text(value: Any) -> str:
    """The TOML literal of a value (as sent over the bus)."""
    return tomli_w.dumps({"v": value}).split("=", 1)[1].strip()


class Configurator:
    """Typed get/set/enumerate over one service's TOML file."""

    def __init__(self, path: Path | str | None, fields: Iterable[ConfigField], *,
                 logger: logging.Logger | None = None, initial: dict[str, Any] | None = None,
                 initial_source: str = "the vehicle profile",
                 validator: Callable[[str, Any], str | None] | None = None) -> None:
        self.path = Path(path) if path else None
        self.validator = validator
        self.fields: dict[str, ConfigField] = {f.name: f for f in fields}
        self._log = logger or logging.getLogger("u2sa_hw.config")
        self._lock = threading.RLock()
        self._values: dict[str, Any] = {n: f.default for n, f in self.fields.items()}
        self._extra: dict[str, Any] = {}
        for name, value in (initial or {}).items():
            self._load_value(name, value, source=initial_source)
        if self.path is not None and self.path.exists():
            self._load_file()

    def _load_file(self) -> None:
        assert self.path is not None
        try:
            data = tomllib.loads(self.path.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{self.path}: not valid TOML ({exc}); fix the file or delete it to use defaults") from None
        except OSError as exc:
            raise ConfigError(f"{self.path}: cannot read ({exc.strerror})") from None
        for name, value in data.items():
            self._load_value(name, value, source=str(self.path))

    def _load_value(self, name: str, value: Any, *, source: str) -> None:
        f = self.fields.get(name)
        if f is None:
            # Kept and written back unchanged: a field of a newer version, or a typo we report.
            self._extra[name] = value
            self._log.warning("%s: unknown config field '%s' ignored (known: %s)", source, name,
                              ", ".join(sorted(self.fields)))
            return
        try:
            self._values[name] = coerce(f, value) if not isinstance(f.default, list) else list(value)
        except ConfigError as exc:
            raise ConfigError(f"{source}: {exc}") from None

    def get(self, name: str) -> Any:
        """The current value of *name* (KeyError names the known fields)."""
        try:
            return self._values[name]
        except KeyError:
            raise KeyError(f"no config field '{name}' (known: {', '.join(sorted(self.fields))})") from None

    def __getitem__(self, name: str) -> Any:
        return self.get(name)

    @contextlib.contextmanager
    def trial(self, name: str, value: Any) -> Iterator[None]:
        """Let :meth:`get` return *value* for *name* inside the block, writing nothing.

        For a validator that checks the whole config as it would be after a change.
        """
        with self._lock:
            old = self._values[name]
            self._values[name] = value
            try:
                yield
            finally:
                self._values[name] = old

    def enumerate(self) -> list[tuple[str, str, Any]]:
        """``(name, type name, value)`` for every declared field."""
        return [(n, f.type_name, self._values[n]) for n, f in self.fields.items()]

    def check(self, name: str, value: Any) -> Any:
        """The coerced value, or ConfigError (unknown field, wrong type, not one of the choices).

        A ``str`` value is text and read by :func:`parse_text` (a TOML literal).
        """
        f = self.fields.get(name)
        if f is None:
            raise ConfigError(f"no config field '{name}' (known: {', '.join(sorted(self.fields))})")
        return parse_text(f, value) if isinstance(value, str) else coerce(f, value)

    def set(self, name: str, value: Any) -> bool:
        """Change *name* and persist the file; False (and a logged error) when refused or unwritable."""
        ok, _ = self.try_set(name, value)
        return ok

    def try_set(self, name: str, value: Any) -> tuple[bool, str]:
        """Like :meth:`set`, returning ``(ok, reason)`` so the bus can send the reason back.

        ``(True, warning)`` with a non-empty warning: the file changed but its directory could
        not be synced (the change is in effect and saved, possibly not durable).

        After the type check the service's *validator* (if any) may refuse the value with a
        reason (a baud rate the driver does not support, a negative rate); nothing is written then.
        """
        try:
            coerced = self.check(name, value)
        except ConfigError as exc:
            self._log.error("config change refused: %s", exc)
            return False, str(exc)
        problem = self.validator(name, coerced) if self.validator else None
        if problem:
            self._log.error("config change refused: field '%s': %s", name, problem)
            return False, f"field '{name}': {problem}"
        with self._lock:
            old = self._values[name]
            self._values[name] = coerced
            try:
                warning = self._write()
            except OSError as exc:
                self._values[name] = old
                reason = f"cannot write {self.path}: {exc.strerror or exc}; the file is unchanged"
                self._log.error("config change of '%s' not saved: %s", name, reason)
                return False, reason
        self._log.info("config '%s' changed from %r to %r", name, old, coerced)
        if warning:
            self._log.warning("config change of '%s': %s", name, warning)
        return True, warning

    def _write(self) -> str:
        """Write the file atomically; OSError when it is unchanged, a warning text when it changed but
        its directory could not be synced (the rename may not survive a power cut), else ""."""
        if self.path is None:
            return ""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        data = {**self._extra, **self._values}
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent)
        try:
            with os.fdopen(fd, "wb") as fh:
                tomli_w.dump(data, fh)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, self.path)
        except BaseException:
            try:
                os.unlink(tmp)
            except OSError:
                pass
            raise
        # From here on the file holds the new value: a failure only weakens durability.
        try:
            dir_fd = os.open(self.path.parent, os.O_RDONLY)
            try:
                os.fsync(dir_fd)
            finally:
                os.close(dir_fd)
        except OSError as exc:
            return (f"saved to {self.path}, but syncing its directory {self.path.parent} failed "
                    f"({exc.strerror or exc}); the change may be lost on a power cut")
        return ""
