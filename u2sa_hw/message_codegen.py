"""Regenerate ``u2sa_hw/lcmtypes`` from the ``.lcm`` files with ``lcm-gen -p``.

The classes with a presence vector (``u2sa_hw.messages.presence.PRESENCE``) get their
presence setters and readers generated into them (``u2sa_hw.message_presence_gen``).

Run ``python -m u2sa_hw.message_codegen`` after editing a ``.lcm`` file, and commit
the result. ``python -m u2sa_hw.message_codegen --check`` exits 1 when the committed
code differs from what lcm-gen makes now (the test suite runs this check).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

MESSAGES_DIR = Path(__file__).resolve().parent / "messages"
GENERATED_DIR = MESSAGES_DIR.parent / "lcmtypes"
LCM_PACKAGE = "u2sa_hw.lcmtypes"
# lcm-gen stamps its own version into __init__.py; the version is not part of the types.
_VERSION_LINE = re.compile(r"^lcm-gen \S+$", re.MULTILINE)


def find_lcm_gen() -> str:
    """Return the path of ``lcm-gen``: beside this Python (the ``lcm`` wheel ships it), else on PATH."""
    beside = Path(sys.executable).with_name("lcm-gen")
    if beside.exists():
        return str(beside)
    found = shutil.which("lcm-gen")
    if not found:
        raise FileNotFoundError(
            "lcm-gen not found: install the 'lcm' package into this environment (pip install lcm)"
        )
    return found


def lcm_sources() -> list[Path]:
    """Every ``.lcm`` file of the message types."""
    return sorted(MESSAGES_DIR.glob("*.lcm"))


def generate(out_dir: Path) -> Path:
    """Run lcm-gen on every ``.lcm`` file into *out_dir*, add the presence methods; return the package dir."""
    from u2sa_hw.message_presence_gen import add_presence
    from u2sa_hw.messages.presence import PRESENCE

    subprocess.run([find_lcm_gen(), "-p", "--ppath", str(out_dir), *map(str, lcm_sources())], check=True)
    package = out_dir.joinpath(*LCM_PACKAGE.split("."))
    for cls, fields in PRESENCE.items():
        path = package / f"{cls}.py"
        path.write_text(add_presence(path.read_text(), cls, fields))
    init = package / "__init__.py"
    init.write_text(lazy_init(init.read_text()))
    return package


_TYPE_IMPORT = re.compile(r"^from \.(\w+) import (\w+) as (\w+)$", re.MULTILINE)
_LAZY_INIT = '''
Made lazy by u2sa_hw.message_codegen: a type's module is imported when the type is first
used (``u2sa_hw.lcmtypes.Health``, ``from u2sa_hw.lcmtypes import Health``), so each service
process holds only the types it uses: all of them cost every process about 2.5 MB. Import a
type from this package, never from its module (``u2sa_hw.lcmtypes.Health.Health``), which
would leave the module where the type belongs.
"""

import importlib as _importlib

_TYPES = (
{types})
__all__ = list(_TYPES)


def __getattr__(name):
    if name in _TYPES:
        cls = getattr(_importlib.import_module(f"{{__name__}}.{{name}}"), name)
        globals()[name] = cls   # after the import, which set the module here: the type replaces it
        return cls
    raise AttributeError(f"module {{__name__!r}} has no attribute {{name!r}}")


def __dir__():
    return sorted(set(globals()) | set(_TYPES))
'''


def lazy_init(text: str) -> str:
    """lcm-gen's package ``__init__.py`` (which imports every type) as a lazy one (PEP 562 ``__getattr__``).

    The docstring (with lcm-gen's version line) is kept; the type names keep lcm-gen's order.
    """
    names = [m.group(1) for m in _TYPE_IMPORT.finditer(text) if m.group(1) == m.group(2) == m.group(3)]
    if not names:
        raise ValueError("lcm-gen's __init__.py names no types: its format changed, see message_codegen.lazy_init")
    head = text[:text.index('"""', 3)].rstrip()
    return head + "\n" + _LAZY_INIT.format(types="".join(f"    {name!r},\n" for name in names))


def _normalised(path: Path) -> str:
    return _VERSION_LINE.sub("lcm-gen", path.read_text())


def differences(generated: Path, committed: Path = GENERATED_DIR) -> list[str]:
    """Names of files that differ between a fresh generation and the committed package."""
    fresh = {p.name for p in generated.glob("*.py")}
    have = {p.name for p in committed.glob("*.py")} if committed.exists() else set()
    diffs = sorted(fresh ^ have)
    for name in sorted(fresh & have):
        if _normalised(generated / name) != _normalised(committed / name):
            diffs.append(name)
    return diffs


def main(argv: list[str] | None = None) -> int:
    """Regenerate (default) or check (``--check``) the committed LCM Python code."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--check", action="store_true", help="compare only; exit 1 on any difference")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        generated = generate(Path(tmp))
        if args.check:
            diffs = differences(generated)
            if diffs:
                print("generated LCM code is stale: " + ", ".join(diffs)
                      + "\nfix: python -m u2sa_hw.message_codegen, then commit u2sa_hw/lcmtypes", file=sys.stderr)
                return 1
            print(f"{LCM_PACKAGE} matches the .lcm files")
            return 0
        if GENERATED_DIR.exists():
            shutil.rmtree(GENERATED_DIR)
        shutil.copytree(generated, GENERATED_DIR)
        print(f"wrote {len(list(GENERATED_DIR.glob('*.py')))} files to {os.path.relpath(GENERATED_DIR)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
