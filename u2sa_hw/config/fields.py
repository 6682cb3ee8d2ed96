"""Config fields (requirement C1, C7): what a service declares of each of its typed variables.

A service declares its fields with defaults (the default's type is the field's type:
int, float, bool, str or list) and what values make sense: ``choices``, bounds
(``ge``/``gt``/``le``/``lt``, for a list field each number in it), ``item_type`` for a list.
Non-finite numbers (inf, -inf, nan) are refused unless a field says ``allow_nonfinite``.
Every number has a finite upper bound (``le``/``lt``, or ``choices``): :func:`field` refuses a
numeric field without one at import, unless it says why with ``unbounded="..."``. A rate is at
most :data:`MAX_RATE_HZ` (or the device's own limit), a period or timeout at most
:data:`MAX_TIMEOUT_S`: ``publish_rate_hz = 1e9`` would spin a core, ``sensor_timeout_s = 1e308``
would never time out.

Text (what ``u2sa param set`` sends) is read as a TOML literal: ``42``, ``2.5``, ``true``,
``"text"``. For a string field a TOML string literal (``"passthrough"`` or ``'passthrough'``)
gives its contents, and any other text (a bare word, ``42``) is taken as it is.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from typing import Any, Callable

TYPE_NAMES = {int: "int", float: "float", bool: "bool", str: "str"}
SECRET_FILE = "secret"   # field(file=SECRET_FILE): the field names a file holding a secret
Bound = int | float
# The ceilings every rate, period and timeout field uses (or a lower one of its own): the loops
# run at most at 1 kHz, and nothing a service waits for is worth waiting more than an hour for.
MAX_RATE_HZ = 1000.0
MAX_TIMEOUT_S = 3600.0
MAX_TIMEOUT_MS = MAX_TIMEOUT_S * 1000.0


class ConfigError(ValueError):
    """A config file or value is invalid; the message names the file/field and the fix."""


@dataclass(frozen=True)
class ConfigField:
    """One declared variable: its name, default (whose type is the field's type), help, and the values allowed.

    ``choices``: the only values allowed. ``ge``/``gt``/``le``/``lt``: bounds (>=, >, <=, <) of a
    number, or of every number in a list. ``allow_nonfinite``: inf, -inf and nan are refused
    unless this is set. ``item_type``: the type of every item of a list field (None: any).
    ``remote``: False for a field a change over the bus must not touch (set in the profile or
    the file, read at the next start); setting it to the value it has is not a change.
    ``file``: True for a str field that names a file (a path relative to the vehicle profile's
    directory, :meth:`VehicleProfile.resolve_path`), ``"secret"`` for one whose file holds a
    secret (a token, a private key); False for anything else (a device path is an address,
    never a file field). ``u2sa check`` and ``u2sa install`` read files from these declarations
    only (:attr:`names_file`, :attr:`secret_file`). ``case_insensitive``: a str value matching a
    choice in another case is taken as that choice's declared spelling (``"ned"`` -> ``"NED"``).
    """

    name: str
    default: Any
    help: str = ""
    choices: tuple[Any, ...] = ()
    ge: Bound | None = None
    gt: Bound | None = None
    le: Bound | None = None
    lt: Bound | None = None
    allow_nonfinite: bool = False
    item_type: type | None = None
    remote: bool = True
    file: bool | str = False
    case_insensitive: bool = False
    unbounded: str = ""

    @property
    def numeric(self) -> bool:
        """True for an int or float field, or a list of them."""
        return self.type in (int, float) or (self.type is list and self.item_type in (int, float))

    @property
    def upper_bound(self) -> Bound | None:
        """The finite largest value allowed (``le``, ``lt`` or the largest choice), None when there is none."""
        limits = [b for b in (self.le, self.lt) if b is not None]
        if self.choices and all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in self.choices):
            limits.append(max(self.choices))
        limits = [b for b in limits if math.isfinite(b)]
        return min(limits) if limits else None

    @property
    def names_file(self) -> bool:
        """True when the value is a path to a file (relative to the profile's directory) the service reads."""
        return self.file is True or self.file == SECRET_FILE

    @property
    def secret_file(self) -> bool:
        """True when the file the value names holds a secret: installed root:u2sa 0640, never world-readable."""
        return self.file == SECRET_FILE

    @property
    def type(self) -> type:
        """The Python type of the field."""
        return type(self.default)

    @property
    def type_name(self) -> str:
        """``int``, ``float``, ``bool``, ``str`` or ``list``."""
        return TYPE_NAMES.get(self.type, self.type.__name__)

    @property
    def bounds(self) -> list[tuple[str, Bound]]:
        """The declared bounds as ``(operator, limit)``: ``(">", 0)``, ``("<=", 100)``."""
        return [(op, limit) for op, limit in ((">=", self.ge), (">", self.gt), ("<=", self.le), ("<", self.lt))
                if limit is not None]

    def range_text(self) -> str:
        """The allowed range in words: ``> 0``, ``>= 0 and <= 100``, or "" when unbounded."""
        return " and ".join(f"{op} {limit:g}" for op, limit in self.bounds)


_BOUND_TESTS: dict[str, Callable[[Bound, Bound], bool]] = {
    ">=": lambda v, b: v >= b, ">": lambda v, b: v > b, "<=": lambda v, b: v <= b, "<": lambda v, b: v < b}


def field(name: str, default: Any, help: str = "", *,  # noqa: A002 - reads well at call sites
          choices: Iterable[Any] = (), ge: Bound | None = None, gt: Bound | None = None,
          le: Bound | None = None, lt: Bound | None = None, allow_nonfinite: bool = False,
          item_type: type | None = None, remote: bool = True, file: bool | str = False,
          case_insensitive: bool = False, unbounded: str = "") -> ConfigField:
    """Declare a config variable (shorthand for :class:`ConfigField`).

    *choices*: the only values allowed; *ge*, *gt*, *le*, *lt*: bounds of a number (or of each
    number of a list); *allow_nonfinite*: accept inf and nan (refused otherwise); *item_type*:
    the type of a list's items; *remote*: False when a change over the bus is refused;
    *case_insensitive*: str choices match in any case and the value becomes the declared spelling.

    A number (or a list of numbers) must have a finite upper bound: *le* or *lt*, or numeric
    *choices*. Rates at most :data:`MAX_RATE_HZ` (or the device's own limit), periods and
    timeouts at most :data:`MAX_TIMEOUT_S`, counts and sizes a sane maximum. A field that truly
    has none says why in *unbounded* (the text is the reason); otherwise it is a TypeError at
    import, so the next field cannot forget it.

    *file*: declare it on every str setting that names a file the service reads (a mission, an
    object list, a token, a certificate): ``file=True``, or ``file="secret"`` when the file holds
    a secret. Its value is then a path relative to the vehicle profile's directory (read it with
    :meth:`VehicleProfile.resolve_path`; empty: no file). ``u2sa check`` makes a non-empty value
    naming no file an error, and ``u2sa install`` copies exactly these files beside the installed
    profile and points the installed profile or config at the copy (a secret one root:u2sa 0640);
    a setting not declared so is never taken for a file, whatever its value. Device paths
    (``/dev/...``) are addresses, not file fields.

    A default that breaks its own declaration is a TypeError or ValueError at import, so a wrong
    declaration never reaches a vehicle.
    """
    if type(default) not in TYPE_NAMES and not isinstance(default, list):
        raise TypeError(f"config field {name}: default must be int, float, bool, str or list, "
                        f"not {type(default).__name__}")
    numeric = type(default) in (int, float) or (isinstance(default, list) and item_type in (int, float))
    bounds = [b for b in (ge, gt, le, lt) if b is not None]
    if bounds and not numeric:
        raise TypeError(f"config field {name}: bounds need a number (or a list with item_type int or float), "
                        f"not {type(default).__name__}")
    if any(isinstance(b, bool) or not isinstance(b, (int, float)) or not math.isfinite(b) for b in bounds):
        raise TypeError(f"config field {name}: bounds must be finite numbers")
    if not (type(file) is bool or file == SECRET_FILE):
        raise ValueError(f"config field {name}: file must be True, False or {SECRET_FILE!r}, not {file!r}")
    if file is not False and type(default) is not str:
        raise TypeError(f"config field {name}: a file field's default must be a str (a path, \"\" for none), "
                        f"not {type(default).__name__}")
    if case_insensitive and not (choices and all(isinstance(c, str) for c in choices)):
        raise TypeError(f"config field {name}: case_insensitive needs str choices")
    f = ConfigField(name, default, help, tuple(choices), ge, gt, le, lt, allow_nonfinite, item_type, remote, file,
                    case_insensitive, unbounded.strip())
    if f.choices and default not in f.choices:
        raise ValueError(f"config field {name}: default {default!r} is not one of its choices {f.choices!r}")
    try:
        coerce(f, default)
    except ConfigError as exc:
        raise ValueError(f"config field {name}: its default breaks its own declaration: {exc}") from None
    if f.numeric and f.upper_bound is None and not f.unbounded:
        raise TypeError(f"config field {name}: a number needs a finite upper bound (le= or lt=; a rate at most "
                        f"{MAX_RATE_HZ:g} Hz, a timeout at most {MAX_TIMEOUT_S:g} s), or unbounded=\"why it has none\"")
    if f.unbounded and not f.numeric:
        raise TypeError(f"config field {name}: unbounded is for a number without an upper bound")
    return f


def choices_text(f: ConfigField) -> str:
    """The allowed values of *f* as TOML literals, comma separated."""
    return ", ".join(to_text(c) for c in f.choices)


def _type_name(value: Any) -> str:
    return TYPE_NAMES.get(type(value), type(value).__name__)


def _checked_number(f: ConfigField, value: Any, *, what: str) -> None:
    """Raise ConfigError when the number *value* is non-finite (unless allowed) or out of *f*'s bounds."""
    if isinstance(value, float) and not math.isfinite(value):
        if f.allow_nonfinite:
            return
        raise ConfigError(f"{what} must be a finite number{' ' + f.range_text() if f.bounds else ''}; "
                          f"got {to_text(value)}")
    for op, limit in f.bounds:
        if not _BOUND_TESTS[op](value, limit):
            raise ConfigError(f"{what} must be {f.range_text()}; got {to_text(value)}")


def _scalar(expected: type, value: Any) -> Any:
    """*value* as *expected* (an int passes as a float), or None when it is not one."""
    if type(value) is expected:
        return value
    if expected is float and type(value) is int:
        return float(value)
    return None


def coerce(f: ConfigField, value: Any) -> Any:
    """*value* as *f*'s type within its choices and bounds, or ConfigError naming the field, the rule and the value.

    An int is accepted for a float field; nothing else is converted (a bool is not an int), but a
    ``case_insensitive`` field's choice in another case becomes its declared spelling.
    """
    expected = f.type
    result = list(value) if expected is list and type(value) is list else _scalar(expected, value)
    if result is None:
        raise ConfigError(f"field '{f.name}' expects {f.type_name}, got {_type_name(value)} {value!r}")
    if f.case_insensitive and isinstance(result, str):   # the declared spelling of a choice written in another case
        result = next((c for c in f.choices if c.lower() == result.lower()), result)
    if f.choices and result not in f.choices:
        any_case = " (any case)" if f.case_insensitive else ""
        raise ConfigError(f"field '{f.name}' must be one of {choices_text(f)}{any_case}; got {to_text(result)}")
    if expected in (int, float):
        _checked_number(f, result, what=f"field '{f.name}'")
    elif expected is list and f.item_type is not None:
        for i, item in enumerate(result):
            checked = _scalar(f.item_type, item)
            if checked is None:
                wanted = TYPE_NAMES.get(f.item_type, f.item_type.__name__)
                raise ConfigError(f"field '{f.name}' item {i} expects {wanted}, got {_type_name(item)} {item!r}")
            if f.item_type in (int, float):
                _checked_number(f, checked, what=f"field '{f.name}' item {i}")
            result[i] = checked
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
    import tomli_w   # imported when first used: a service that never writes its config never loads it
    return tomli_w.dumps({"v": value}).split("=", 1)[1].strip()
