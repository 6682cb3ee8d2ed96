"""Parameter files: every service's config in one TOML file, saved from the bus and loaded back.

``u2sa param save FILE`` writes what the services on the bus report (as ArduPilot's .param
files or ``ros2 param dump`` do); ``u2sa param load FILE`` compares a file with what the
services report now, prints the differences and applies them. This module is the file half,
with no bus: :func:`render` writes a file, :func:`plan_load` checks one against the live
values and lists the changes, :func:`key_lines` finds the line of every key.

The file, one table per service::

    # u2sa parameters of vehicle 'rover' (system id 1, profile /etc/u2sa/vehicle.toml)
    # saved 2025-06-01T12:00:00+02:00 by u2sa param save: 12 services on the bus

    [estimator]
    kind = "state_estimator"

    [estimator.params]
    publish_rate_hz = 50.0
    sensor_timeout_s = 2.0

``kind`` is the service's kind (a load refuses the table when the service of that name on the
bus is of another kind); ``params`` holds the typed values. The kind lives beside ``params``
rather than among the fields so that no field name can ever collide with it. A hand-written
file may leave ``kind`` out and list only the fields it changes: a field not in the file is
left as it is.

Checks, each refused with the file and line before anything is changed: a service not on the
bus, a field the service does not have (with a did-you-mean), a value of the wrong type, not
one of the field's choices or out of its range (the kind's declared fields, the same check
the service makes), and a change of a field the service does not take over the bus
(``remote=False``).

tomllib gives no line numbers, so :func:`key_lines` scans the text for them (strings,
multi-line strings, arrays and inline tables are skipped as values, so a ``key =`` inside a
string is never taken for a key).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Mapping

from u2sa_hw.config.fields import ConfigError, ConfigField, coerce, to_text
from u2sa_hw.config.keys import did_you_mean, known_text, unknown_key_problem

PARAMS = "params"   # the sub-table of a service that holds its fields
KIND = "kind"       # the key beside it that names the service's kind


@dataclass
class LiveService:
    """What the bus says about one service: its name, kind ("" when unknown) and fields (name -> (type, TOML text))."""

    name: str
    kind: str
    service_type: str
    fields: dict[str, tuple[str, str]]
    declared: Mapping[str, ConfigField] | None = None   # the kind's declared fields, when they match the live ones


@dataclass
class Change:
    """One field of one service to change: from the live text to *new_text* (declared at *line* of the file)."""

    service: str
    field: str
    old_text: str
    new_text: str
    line: int


@dataclass
class LoadPlan:
    """What loading a file would do: the changes per service (file order), the problems, the fields already equal."""

    changes: dict[str, list[Change]] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    unchanged: int = 0

    @property
    def count(self) -> int:
        """The number of changes."""
        return sum(len(c) for c in self.changes.values())


# -- writing -------------------------------------------------------------------------------

def _key(name: str) -> str:
    import tomli_w
    return tomli_w.dumps({name: 0}).split("=", 1)[0].strip()


def render(services: Iterable[LiveService], header: Iterable[str]) -> str:
    """The text of a parameter file: *header* lines as comments, then one table per service."""
    out = [f"# {line}".rstrip() for line in header]
    for s in services:
        out.append("")
        out.append(f"[{_key(s.name)}]")
        if s.kind:
            out.append(f"{KIND} = {to_text(s.kind)}")
        else:
            out.append(f"# kind not known here (no profile names it): service type {s.service_type!r}")
        out.append("")
        out.append(f"[{_key(s.name)}.{PARAMS}]")
        for name, (_type_name, text) in s.fields.items():
            out.append(f"{_key(name)} = {text}")
    return "\n".join(out) + "\n"


# -- line numbers --------------------------------------------------------------------------

_BARE = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_-")


def _string_end(text: str, i: int) -> int:
    """The index after the string starting at *i* (basic, literal or multi-line)."""
    for quote in ('"""', "'''"):
        if text.startswith(quote, i):
            j = i + 3
            while j < len(text):
                if quote[0] == '"' and text[j] == "\\":
                    j += 2
                    continue
                if text.startswith(quote, j):
                    j += 3
                    extra = 0
                    while extra < 2 and j < len(text) and text[j] == quote[0]:   # """a"""" ends with a quote
                        j, extra = j + 1, extra + 1
                    return j
                j += 1
            return j
    quote, j = text[i], i + 1
    while j < len(text) and text[j] != quote and text[j] != "\n":
        j += 2 if quote == '"' and text[j] == "\\" else 1
    return j + 1


def _dotted_key(text: str, i: int, stop: str) -> tuple[tuple[str, ...], int]:
    """The dotted key starting at *i* (bare or quoted parts), up to *stop*; and the index of *stop*."""
    parts: list[str] = []
    while i < len(text):
        c = text[i]
        if c in " \t.":
            i += 1
        elif c in "\"'":
            end = _string_end(text, i)
            try:
                parts.append(tomllib.loads(f"k = {text[i:end]}")["k"])
            except tomllib.TOMLDecodeError:
                parts.append(text[i + 1:end - 1])
            i = end
        elif c in _BARE:
            j = i
            while j < len(text) and text[j] in _BARE:
                j += 1
            parts.append(text[i:j])
            i = j
        else:
            break
    return tuple(parts), i


def _value_end(text: str, i: int) -> int:
    """The index of the newline ending the value at *i* (arrays and inline tables may span lines)."""
    depth = 0
    while i < len(text):
        c = text[i]
        if c in "\"'":
            i = _string_end(text, i)
            continue
        if c == "#":
            while i < len(text) and text[i] != "\n":
                i += 1
            continue
        if c in "[{":
            depth += 1
        elif c in "]}":
            depth -= 1
        elif c == "\n" and depth <= 0:
            return i
        i += 1
    return i


def key_lines(text: str) -> dict[tuple[str, ...], int]:
    """The 1-based line of every table header and key of a TOML *text*, by its full dotted path.

    ``[estimator.params]`` on line 5 and ``rate = 1`` on line 6 give ``("estimator", "params"): 5``
    and ``("estimator", "params", "rate"): 6``. Meant for text tomllib has accepted.
    """
    lines: dict[tuple[str, ...], int] = {}
    table: tuple[str, ...] = ()
    i = 0
    while i < len(text):
        c = text[i]
        if c in " \t\r\n\ufeff":
            i += 1
        elif c == "#":
            while i < len(text) and text[i] != "\n":
                i += 1
        elif c == "[":
            start = i
            i += 2 if text.startswith("[[", i) else 1
            table, i = _dotted_key(text, i, "]")
            lines.setdefault(table, text.count("\n", 0, start) + 1)
            while i < len(text) and text[i] != "\n":
                i += 1
        else:
            start = i
            key, i = _dotted_key(text, i, "=")
            if not key:   # not a key (the text is not TOML): skip the line
                i = _value_end(text, i + 1)
                continue
            lines.setdefault(table + key, text.count("\n", 0, start) + 1)
            i = _value_end(text, i + 1)
    return lines


# -- loading -------------------------------------------------------------------------------

def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return type(a) is type(b) and a == b


def _live_value(type_name: str, text: str) -> Any:
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def plan_load(label: str, text: str, on_bus: Iterable[str], live: Mapping[str, LiveService], *,
              only: Iterable[str] = ()) -> LoadPlan:
    """Check the parameter file *text* (named *label* in messages) against the *live* services.

    *on_bus*: every service name discovery found (for the did-you-mean of one that is not
    there); *live*: the config of those the file names; *only*: the tables to load (all when
    empty; one not in the file is a problem). Every problem is one line starting
    ``LABEL:LINE:``. A value is checked against the kind's declared field when
    :attr:`LiveService.declared` has it, else against the live value's type.
    """
    plan = LoadPlan()
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        plan.problems.append(f"{label}: not valid TOML ({exc})")
        return plan
    lines = key_lines(text)
    names = sorted(on_bus)

    def line_of(*path: str) -> int:   # the key's line, else its table's (an inline table), else 0
        for n in range(len(path), 0, -1):
            if path[:n] in lines:
                return lines[path[:n]]
        return 0

    def at(*path: str) -> str:
        line = line_of(*path)
        return f"{label}:{line}" if line else label

    wanted = list(only)
    for name in wanted:
        if name not in data:
            hint = did_you_mean(name, data)
            plan.problems.append(f"{label}: no table [{name}] in the file" + (f"; {hint}" if hint else "") +
                                 f" (tables: {known_text(data)})")
    for service, table in data.items():
        if wanted and service not in wanted:
            continue
        if not isinstance(table, dict):
            plan.problems.append(f"{at(service)}: '{service}' is not a table: a parameter file holds one table "
                                 f"per service, [{service}] with kind and [{service}.{PARAMS}] with the fields")
            continue
        if service not in live:
            hint = did_you_mean(service, names)
            plan.problems.append(f"{at(service)}: no service '{service}' on the bus" + (f"; {hint}" if hint else "") +
                                 f" (services: {known_text(names)})")
            continue
        s = live[service]
        for key in table:
            if key not in (KIND, PARAMS):
                plan.problems.append(f"{at(service, key)}: [{service}]: unknown key '{key}' (a service's table "
                                     f"holds {KIND} and {PARAMS}; its fields go under [{service}.{PARAMS}])")
        kind = table.get(KIND)
        if kind is not None and s.kind and kind != s.kind:
            plan.problems.append(f"{at(service, KIND)}: [{service}]: the file's kind is '{kind}', but '{service}' on "
                                 f"the bus is a {s.kind}; nothing of it is loaded")
            continue
        params = table.get(PARAMS, {})
        if not isinstance(params, dict):
            plan.problems.append(f"{at(service, PARAMS)}: [{service}]: {PARAMS} must be a table of fields")
            continue
        changes: list[Change] = []
        for fname, value in params.items():
            where = at(service, PARAMS, fname)
            if fname not in s.fields:
                plan.problems.append(unknown_key_problem(fname, s.fields, where=f"{where}: {service}", what="field"))
                continue
            type_name, old_text = s.fields[fname]
            current = _live_value(type_name, old_text)
            declared = (s.declared or {}).get(fname)
            try:
                new = coerce(declared or ConfigField(fname, current), value)
            except ConfigError as exc:
                plan.problems.append(f"{where}: {service}: {exc}")
                continue
            if _same(new, current):
                plan.unchanged += 1
                continue
            if declared is not None and not declared.remote:
                plan.problems.append(f"{where}: {service}: field '{fname}' is not changed over the bus "
                                     f"(it is read at start: set it in the profile's settings or the service's "
                                     f"config file); it is {old_text} there, the file says {to_text(new)}")
                continue
            changes.append(Change(service, fname, old_text, to_text(new), line_of(service, PARAMS, fname)))
        if changes:
            plan.changes[service] = changes
    return plan


def declared_for(kind: str, live_fields: Iterable[str],
                 lookup: Callable[[str], Mapping[str, ConfigField]] | None = None) -> Mapping[str, ConfigField] | None:
    """The fields *kind* declares when they are exactly the live ones (this checkout knows that service), else None."""
    if not kind:
        return None
    if lookup is None:
        from u2sa_hw.service.validate import declared_fields as lookup
    try:
        fields = lookup(kind)
    except (LookupError, ImportError):
        return None
    return fields if set(fields) == set(live_fields) else None
