"""A udev rules parser in Python, for checking rules files where ``udevadm`` is not installed.

It follows udev(7): a rule is one line (a trailing backslash continues it) of
comma-separated ``KEY[{attribute}] OPERATOR "value"`` expressions. It refuses what udev
refuses or ignores with a complaint: an unknown key, an operator the key does not take
(a match key assigned, an assignment key compared), a missing or unknown ``{attribute}``
where the key needs one, an unquoted or unterminated value, expressions not separated by
commas, an unknown ``$name``/``%x`` substitution in a value udev substitutes, and a MODE
that is not octal. Each problem names ``FILE:LINE``.

:func:`matches` applies a rule's match keys to a device described as a dict, with udev's
glob patterns (``*``, ``?``, ``[...]``, ``|`` alternatives), so a test can check that a
rule names the device it should.
"""

from __future__ import annotations

import fnmatch
import re
from dataclasses import dataclass, field
from typing import Any

MATCH_OPS = ("==", "!=")
ASSIGN_OPS = ("=", "+=", "-=", ":=")
# key -> (needs an {attribute}: True / False / "optional", allowed operators)
KEYS: dict[str, tuple[bool | str, tuple[str, ...]]] = {
    "ACTION": (False, MATCH_OPS), "DEVPATH": (False, MATCH_OPS), "KERNEL": (False, MATCH_OPS),
    "KERNELS": (False, MATCH_OPS), "SUBSYSTEM": (False, MATCH_OPS), "SUBSYSTEMS": (False, MATCH_OPS),
    "DRIVER": (False, MATCH_OPS), "DRIVERS": (False, MATCH_OPS), "ATTRS": (True, MATCH_OPS),
    "TAGS": (False, MATCH_OPS), "TEST": ("optional", MATCH_OPS), "PROGRAM": (False, MATCH_OPS),
    "RESULT": (False, MATCH_OPS), "CONST": (True, MATCH_OPS),
    "NAME": (False, MATCH_OPS + ("=", ":=")), "SYMLINK": (False, MATCH_OPS + ASSIGN_OPS),
    "ATTR": (True, MATCH_OPS + ("=", ":=")), "SYSCTL": (True, MATCH_OPS + ("=", ":=")),
    "ENV": (True, MATCH_OPS + ASSIGN_OPS), "TAG": (False, MATCH_OPS + ASSIGN_OPS),
    "OWNER": (False, ("=", ":=")), "GROUP": (False, ("=", ":=")), "MODE": (False, ("=", ":=")),
    "SECLABEL": (True, ("=", "+=", ":=")), "RUN": ("optional", ASSIGN_OPS), "LABEL": (False, ("=",)),
    "GOTO": (False, ("=",)), "IMPORT": (True, MATCH_OPS + ("=", "+=", ":=")), "OPTIONS": (False, ("=", "+=", ":=")),
}
ATTRIBUTE_CHOICES = {"RUN": {"program", "builtin"}, "IMPORT": {"program", "builtin", "file", "db", "cmdline", "parent"}}
# values udev runs through its substitution (udev(7) "string substitutions")
SUBSTITUTED = {"NAME", "SYMLINK", "OWNER", "GROUP", "MODE", "RUN", "ENV", "ATTR", "PROGRAM", "IMPORT", "SECLABEL",
               "SYSCTL"}
DOLLAR_NAMES = {"devpath", "kernel", "number", "driver", "attr", "sysctl", "env", "major", "minor", "result",
                "parent", "name", "links", "root", "sys", "devnode"}
PERCENT_LETTERS = set("pkndsEMmcPDLrSN%")
_KEY = re.compile(r"[A-Z_]+")


@dataclass(frozen=True)
class Expression:
    """``key{attribute} op "value"``."""

    key: str
    attribute: str | None
    op: str
    value: str


@dataclass
class Rule:
    """One rule: its file, first line and expressions."""

    file: str
    line: int
    expressions: list[Expression] = field(default_factory=list)

    def assignments(self, key: str) -> list[Expression]:
        """The assignment expressions of *key*."""
        return [e for e in self.expressions if e.key == key and e.op in ASSIGN_OPS]


class RulesSyntaxError(ValueError):
    """One or more problems, each ``FILE:LINE: text``."""

    def __init__(self, problems: list[str]) -> None:
        self.problems = problems
        super().__init__("\n".join(problems))


def _logical_lines(text: str) -> list[tuple[int, str]]:
    lines, buffer, start = [], "", 0
    for number, raw in enumerate(text.splitlines(), 1):
        if not buffer:
            start = number
            if raw.lstrip().startswith("#") or not raw.strip():
                continue
        if raw.endswith("\\"):
            buffer += raw[:-1]
            continue
        lines.append((start, buffer + raw))
        buffer = ""
    if buffer:
        lines.append((start, buffer + "\\"))  # a continuation into the end of the file
    return lines


def _check_substitutions(value: str) -> str | None:
    for match in re.finditer(r"\$(\$|[a-z]+)", value):
        if match.group(1) != "$" and match.group(1) not in DOLLAR_NAMES:
            return f"unknown substitution ${match.group(1)}"
    for match in re.finditer(r"%(.)", value):
        if match.group(1) not in PERCENT_LETTERS:
            return f"unknown substitution %{match.group(1)}"
    return None


def _parse_expression(text: str, pos: int) -> tuple[Expression, int]:
    """One expression starting at *pos* (no leading blanks); returns it and the position after it."""
    key_match = _KEY.match(text, pos)
    if not key_match:
        raise ValueError(f"expected a key at {text[pos:pos + 20]!r}")
    key, pos = key_match.group(), key_match.end()
    if key not in KEYS:
        raise ValueError(f"unknown key {key}")
    needs, ops = KEYS[key]
    attribute = None
    if text.startswith("{", pos):
        end = text.find("}", pos)
        if end < 0:
            raise ValueError(f"{key}: unterminated {{attribute}}")
        attribute, pos = text[pos + 1:end], end + 1
        if not attribute:
            raise ValueError(f"{key}: empty {{attribute}}")
        if key in ATTRIBUTE_CHOICES and attribute not in ATTRIBUTE_CHOICES[key]:
            raise ValueError(f"{key}{{{attribute}}}: the type must be one of {sorted(ATTRIBUTE_CHOICES[key])}")
    elif needs is True:
        raise ValueError(f"{key} needs an {{attribute}}, e.g. {key}{{name}}")
    if needs is False and attribute is not None:
        raise ValueError(f"{key} takes no {{attribute}}")
    while pos < len(text) and text[pos] in " \t":
        pos += 1
    op = next((o for o in ("==", "!=", "+=", "-=", ":=", "=") if text.startswith(o, pos)), None)
    if op is None:
        raise ValueError(f"{key}: expected an operator (==, !=, =, +=, -=, :=)")
    if op not in ops:
        raise ValueError(f"{key} does not take the operator {op} (it takes {', '.join(ops)})")
    pos += len(op)
    while pos < len(text) and text[pos] in " \t":
        pos += 1
    if not text.startswith('"', pos):
        raise ValueError(f"{key}: the value must be in double quotes")
    pos += 1
    value = []
    while True:
        if pos >= len(text):
            raise ValueError(f"{key}: unterminated quoted value")
        char = text[pos]
        if char == "\\" and pos + 1 < len(text) and text[pos + 1] == '"':
            value.append('"')
            pos += 2
            continue
        if char == '"':
            return Expression(key, attribute, op, "".join(value)), pos + 1
        value.append(char)
        pos += 1


def parse_rule(text: str, *, file: str, line: int) -> Rule:
    """One logical rule line; ValueError (without the place) on the first problem."""
    rule, pos = Rule(file, line), 0
    while True:
        while pos < len(text) and text[pos] in " \t":
            pos += 1
        if pos >= len(text):
            break
        expression, pos = _parse_expression(text, pos)
        rule.expressions.append(expression)
        while pos < len(text) and text[pos] in " \t":
            pos += 1
        if pos < len(text):
            if text[pos] != ",":
                raise ValueError(f"expected ',' after {expression.key}, got {text[pos:pos + 20]!r}")
            pos += 1
            if not text[pos:].strip():
                raise ValueError("a rule ends with ','")
    for e in rule.expressions:
        if e.key in SUBSTITUTED and e.op in ASSIGN_OPS and (why := _check_substitutions(e.value)):
            raise ValueError(f"{e.key}: {why}")
        if e.key == "MODE" and not re.fullmatch(r"0?[0-7]{3,4}", e.value):
            raise ValueError(f'MODE="{e.value}" is not an octal mode like "0660"')
        if e.key == "SYMLINK" and e.op in ASSIGN_OPS and e.value.startswith("/"):
            raise ValueError(f'SYMLINK="{e.value}" must be relative to /dev')
    return rule


def parse_rules(text: str, *, file: str) -> list[Rule]:
    """Every rule of one file; RulesSyntaxError lists every problem as ``FILE:LINE: text``."""
    rules, problems = [], []
    for number, line in _logical_lines(text):
        if line.endswith("\\"):
            problems.append(f"{file}:{number}: the line continues (\\) past the end of the file")
            continue
        try:
            rules.append(parse_rule(line, file=file, line=number))
        except ValueError as exc:
            problems.append(f"{file}:{number}: {exc}")
    if problems:
        raise RulesSyntaxError(problems)
    return rules


def _glob(value: str, pattern: str) -> bool:
    return any(fnmatch.fnmatchcase(value, alternative) for alternative in pattern.split("|"))


def matches(rule: Rule, device: dict[str, Any]) -> bool:
    """Whether *rule*'s match keys hold for *device*: ``{"SUBSYSTEM": "tty", "ATTRS": {"idVendor": ...}}``
    (ATTRS and ENV as dicts; a key the device lacks does not match ``==``)."""
    for e in rule.expressions:
        if e.op not in MATCH_OPS:
            continue
        have = device.get(e.key)
        if e.attribute is not None:
            have = (have or {}).get(e.attribute)
        hit = have is not None and _glob(str(have), e.value)
        if hit != (e.op == "=="):
            return False
    return True
