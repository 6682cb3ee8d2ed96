"""MCAP schemas for LCM types: the ``.lcm`` definitions a message needs, as text.

A schema holds the struct itself and every struct it uses (parents and nested types),
dependencies first, so a log carries everything needed to decode it without this code.
"""

from __future__ import annotations

import re
from functools import lru_cache
from pathlib import Path

MESSAGES_DIR = Path(__file__).resolve().parent.parent / "messages"
SCHEMA_ENCODING = "lcm"
MESSAGE_ENCODING = "lcm"
_STRUCT = re.compile(r"((?://[^\n]*\n)*)struct\s+(\w+)\s*\{[^}]*\}", re.MULTILINE)


@lru_cache(maxsize=1)
def struct_definitions() -> dict[str, str]:
    """Struct name -> its ``.lcm`` text (with the comment lines above it)."""
    out: dict[str, str] = {}
    for path in sorted(MESSAGES_DIR.glob("*.lcm")):
        for match in _STRUCT.finditer(path.read_text()):
            out[match.group(2)] = match.group(0).strip()
    return out


def _dependencies(cls: type, seen: list[str]) -> None:
    for type_name in cls.__typenames__:
        if "." not in type_name:
            continue
        short = type_name.rsplit(".", 1)[1]
        if short in seen:
            continue
        from u2sa_hw.messages import REGISTRY

        _dependencies(REGISTRY.by_name(short), seen)
        if short not in seen:
            seen.append(short)


@lru_cache(maxsize=None)
def schema_text(cls: type) -> str:
    """The ``.lcm`` text of *cls* and everything it uses, dependencies first."""
    names: list[str] = []
    _dependencies(cls, names)
    names.append(cls.__name__)
    defs = struct_definitions()
    body = "\n\n".join(defs[n] for n in names if n in defs)
    return f"package u2sa_hw.lcmtypes;\n\n{body}\n"
