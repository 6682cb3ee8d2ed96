"""Configurator (requirement C1, C7): a per-service TOML file of typed variables.

The fields (types, choices, bounds, the text literals ``u2sa param set`` sends) are declared
with :func:`u2sa_hw.config.fields.field`; this is the file of their values.

A missing file means defaults; the file is created on the first change over the bus. The
file holds only what was read from it or changed over the bus, never a value that came from
the profile's settings or a default: otherwise one unrelated change would freeze the profile's
values into the file, which overrides the profile (a bench profile's ``rc_gating = false``
would outlive the switch to the vehicle profile).
Every value -- from the file, from the profile's settings, from a change over the bus -- is
checked against its field; a refusal names the field, the rule (expected type, allowed
values, bound) and the value, and for a file or the profile the file. A change is refused
before anything is written, so the file is untouched. Writes are atomic (temp file in the
same directory, fsync, rename), so a crash or a full disk never leaves a half-written file;
an unwritable file makes ``set`` return False and logs why. An unknown key in the profile's
settings is an error with a did-you-mean; in the file it is a warning and kept (a field of a
newer version). An address setting of the old profile form (``port``, ``bus``, ``chip``...)
given to a driver (a service with a ``device`` setting), in either, is an error naming the new
form (:func:`u2sa_hw.config.keys.old_form_problem`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import tomllib
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from u2sa_hw.config.fields import ConfigError, ConfigField, coerce, parse_text
from u2sa_hw.config.keys import did_you_mean, known_text, old_form_keys, old_form_problem, unknown_key_problem


class Configurator:
    """Typed get/set/enumerate over one service's TOML file (read-only, it is also a Mapping).

    *initial*: the profile's settings, checked strictly (an unknown key is an error), except
    keys in *passthrough* (settings some other layer reads, not fields). *validator*: called
    with a type-checked change before it is written; a returned text refuses it.
    """

    def __init__(self, path: Path | str | None, fields: Iterable[ConfigField], *,
                 logger: logging.Logger | None = None, initial: dict[str, Any] | None = None,
                 initial_source: str = "the vehicle profile",
                 validator: Callable[[str, Any], str | None] | None = None,
                 passthrough: Iterable[str] = ()) -> None:
        self.path = Path(path) if path else None
        self.validator = validator
        self.passthrough = frozenset(passthrough)
        self.fields: dict[str, ConfigField] = {f.name: f for f in fields}
        self._log = logger or logging.getLogger("u2sa_hw.config.configurator")
        self._lock = threading.RLock()
        self._values: dict[str, Any] = {n: f.default for n, f in self.fields.items()}
        self._extra: dict[str, Any] = {}
        self._persisted: set[str] = set()   # fields the file holds: read from it or changed over the bus
        self._trial = threading.local()      # a proposed value, seen only by the thread validating it
        self._trials = 0                     # trials open in any thread: get() skips the thread-local when 0
        self._trials_lock = threading.Lock()
        device = (initial or {}).get("device")
        self._device_hint = device.strip() if isinstance(device, str) and device.strip() else "NAME"
        for name, value in (initial or {}).items():
            if name not in self.passthrough:
                self._load_value(name, value, source=initial_source, strict=True)
        if self.path is not None and self.path.exists():
            self._load_file()

    def _load_file(self) -> None:
        assert self.path is not None
        try:
            text = self.path.read_bytes().decode("utf-8")
            data = tomllib.loads(text)
        except UnicodeDecodeError as exc:
            raise ConfigError(f"{self.path}: not a text file (byte {exc.start} is 0x{exc.object[exc.start]:02x}, "
                              "not UTF-8); fix the file or delete it to use defaults") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{self.path}: not valid TOML ({exc}); fix the file or delete it to use defaults") from None
        except OSError as exc:
            raise ConfigError(f"{self.path}: cannot read ({exc.strerror})") from None
        for name, value in data.items():
            self._load_value(name, value, source=str(self.path))
            if name in self.fields:
                self._persisted.add(name)

    def _load_value(self, name: str, value: Any, *, source: str, strict: bool = False) -> None:
        f = self.fields.get(name)
        if f is None:
            if old_form_keys({name: value}, self.fields):   # a driver's address setting of the old form
                raise ConfigError(str(old_form_problem(name, where=source, device=self._device_hint)))
            if strict:   # the profile's settings: a typo there is an error (the profile is checked as a whole)
                raise ConfigError(unknown_key_problem(name, self.fields, where=source))
            # Kept and written back unchanged: a field of a newer version, or a typo we report.
            self._extra[name] = value
            hint = did_you_mean(name, self.fields)
            self._log.warning("%s: unknown config field '%s' ignored%s (known: %s)", source, name,
                              f"; {hint}" if hint else "", known_text(self.fields))
            return
        try:
            self._values[name] = coerce(f, value)
        except ConfigError as exc:
            raise ConfigError(f"{source}: {exc}; fix it there") from None

    def get(self, name: str, *default: Any) -> Any:
        """The current value of *name*; for an unknown name *default* if given, else KeyError naming the known fields.

        With a default it reads like a mapping's ``get``, so code that takes a plain settings dict
        takes a Configurator too.
        """
        if self._trials:   # drivers read settings per frame: the thread-local only when it can matter
            trial = getattr(self._trial, "values", None)
            if trial and name in trial:
                return trial[name]
        try:
            return self._values[name]
        except KeyError:
            if default:
                return default[0]
            raise KeyError(f"no config field '{name}' (known: {', '.join(sorted(self.fields))})") from None

    def __getitem__(self, name: str) -> Any:
        return self.get(name)

    def __contains__(self, name: object) -> bool:
        return name in self._values

    def __iter__(self) -> Iterator[str]:
        return iter(list(self._values))

    def __len__(self) -> int:
        return len(self._values)

    @contextlib.contextmanager
    def trial(self, name: str, value: Any) -> Iterator[None]:
        """Let :meth:`get` return *value* for *name* inside the block, in this thread only, writing nothing.

        For a validator that checks the whole config as it would be after a change. Other
        threads keep seeing the live value: a proposal that is then refused (a dead-man timeout
        of 0) never takes effect, not even for the moment it is checked.
        """
        if name not in self._values:
            raise KeyError(f"no config field '{name}' (known: {', '.join(sorted(self.fields))})")
        previous = getattr(self._trial, "values", None)
        with self._trials_lock:
            self._trials += 1
        self._trial.values = {**(previous or {}), name: value}
        try:
            yield
        finally:
            self._trial.values = previous
            with self._trials_lock:
                self._trials -= 1

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
            was_persisted = name in self._persisted
            self._values[name] = coerced
            self._persisted.add(name)
            try:
                warning = self._write()
            except OSError as exc:
                self._values[name] = old
                if not was_persisted:
                    self._persisted.discard(name)
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
        data = {**self._extra, **{n: v for n, v in self._values.items() if n in self._persisted}}
        import tempfile
        import tomli_w
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
