"""Unknown keys in a profile or config table: one line each, with a did-you-mean.

Every table of the vehicle profile (``[vehicle]``, ``[services.X]``, its ``settings`` and
``supervision``, ``[simulation]``, ``[devices.X]``) is checked with :func:`unknown_key_problems`,
so a typo (``log_levle``, ``prot``) is an error that names the file, the key and the fix
instead of a value silently left at its default.

    >>> did_you_mean("prot", ["port", "baudrate"])
    "did you mean 'port'?"
    >>> unknown_key_problems({"prot": 1}, ["port", "baudrate"], where="vehicle.toml [services.gps] settings")
    ["vehicle.toml [services.gps] settings: unknown key 'prot'; did you mean 'port'? (known: baudrate, port)"]
"""

from __future__ import annotations

from typing import Iterable, Mapping

# difflib's own default: a swapped pair in a short word still matches ("prot" -> "port" scores 0.75),
# and below it suggestions turn into noise.
_CUTOFF = 0.6
_MAX_LISTED = 30   # a table with more known keys lists the closest few instead of all


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """``"did you mean 'X'?"`` for the choice closest to *word* (a case-insensitive match first), else ""."""
    options = [str(c) for c in choices]
    for option in options:
        if option.lower() == word.lower() and option != word:
            return f"did you mean '{option}'?"
    import difflib   # only when a key is misspelt
    close = difflib.get_close_matches(word, options, n=1, cutoff=_CUTOFF)
    return f"did you mean '{close[0]}'?" if close else ""


def known_text(choices: Iterable[str]) -> str:
    """The known keys, sorted and comma separated (``none`` when there are none)."""
    names = sorted(str(c) for c in choices)
    if len(names) > _MAX_LISTED:
        names = names[:_MAX_LISTED] + [f"... ({len(names) - _MAX_LISTED} more)"]
    return ", ".join(names) or "none"


def unknown_key_problem(key: str, known: Iterable[str], *, where: str, what: str = "key") -> str:
    """One line: *where*, the unknown *key* (a *what*: "key", "service kind"...), a did-you-mean, the known ones."""
    options = list(known)
    hint = did_you_mean(key, options)
    return f"{where}: unknown {what} '{key}'" + (f"; {hint}" if hint else "") + f" (known: {known_text(options)})"


def unknown_key_problems(table: Mapping[str, object], known: Iterable[str], *, where: str,
                         what: str = "key") -> list[str]:
    """One line per key of *table* not in *known* (see :func:`unknown_key_problem`); [] when all are known."""
    options = list(known)
    allowed = set(options)
    return [unknown_key_problem(str(k), options, where=where, what=what) for k in table if k not in allowed]
