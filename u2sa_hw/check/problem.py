"""One finding of ``u2sa check``: severity, file, key, what is wrong and the fix, printed as one line."""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Iterable

ERROR = "error"
WARNING = "warning"


@dataclass(frozen=True)
class Problem:
    """One finding: an ``error`` stops run/sim/install, a ``warning`` does not.

    *file* is the file the key is in (the profile, a service's config file, a referenced
    file), *key* the TOML path inside it (``services.gps.settings.baudrate``; empty for the
    file as a whole), *message* what is wrong and *fix* what to do about it.
    """

    severity: str
    file: str
    key: str
    message: str
    fix: str = ""

    def __str__(self) -> str:
        where = f"{self.file} [{self.key}]" if self.key else self.file
        fix = f"; fix: {self.fix}" if self.fix else ""
        return f"{self.severity}: {where}: {self.message}{fix}"

    @property
    def is_error(self) -> bool:
        """True for an error (warnings do not fail a check)."""
        return self.severity == ERROR

    def to_dict(self) -> dict[str, str]:
        """The problem as a JSON-ready dict."""
        return asdict(self)


def errors_of(problems: Iterable[Problem]) -> list[Problem]:
    """The errors among *problems*."""
    return [p for p in problems if p.is_error]


def did_you_mean(word: object, known: Iterable[object]) -> str:
    """`` (did you mean 'x'?)`` when *word* is close to one of *known*, else ``""`` (config_keys' rule)."""
    from u2sa_hw.config.keys import did_you_mean as hint_for

    hint = hint_for(str(word), [str(k) for k in known])
    return f" ({hint})" if hint else ""


class Collector:
    """Gathers problems for one profile; each check adds to it and never stops the others."""

    def __init__(self, profile_path: Path) -> None:
        self.profile_path = str(profile_path)
        self.problems: list[Problem] = []

    def error(self, key: str, message: str, fix: str, *, file: Path | str | None = None) -> None:
        """Add an error in *file* (default: the profile) at *key*."""
        self.problems.append(Problem(ERROR, str(file or self.profile_path), key, message, fix))

    def warning(self, key: str, message: str, fix: str, *, file: Path | str | None = None) -> None:
        """Add a warning in *file* (default: the profile) at *key*."""
        self.problems.append(Problem(WARNING, str(file or self.profile_path), key, message, fix))

    def from_text(self, text: str, *, key: str, fix: str, file: Path | str | None = None,
                  severity: str = ERROR) -> None:
        """Add a problem from another module's one-line error (``FILE [table] what; fix``).

        The file and table prefix the text repeats are stripped; a ``; `` clause after the first
        becomes the fix when the text carries one, else *fix* is used.
        """
        file = str(file or self.profile_path)
        text = str(text).strip()
        for prefix in (file, self.profile_path, "the vehicle profile"):
            if text.startswith(prefix):
                text = text[len(prefix):].lstrip(": ")
                break
        found = re.match(r"\[([^\]]+)\]((?:\.[\w.]+)?)\s*:?\s*(.*)", text, re.S)
        if found:
            table = found.group(1) + found.group(2)   # "[safety].manual_mixer" -> safety.manual_mixer
            if not key or table.startswith(key):
                key = table   # the more precise of the two
            text = found.group(3)
        message, sep, given_fix = text.partition("; ")
        if sep and len(message) > 12:
            text, fix = message, given_fix
        self.problems.append(Problem(severity, file, key, text.rstrip("."), fix))


def type_name(value: Any) -> str:
    """``int``, ``str``, ``list``... of a TOML value, for messages."""
    return {bool: "bool", int: "int", float: "float", str: "str", list: "list", dict: "table"}.get(
        type(value), type(value).__name__)
