"""The layout's one-way dependency rule (DESIGN.md section 1, docs/ports.md "Where each thing goes").

``drivers/``, ``hil/``, ``mock_devices/`` and ``simulation/`` (installed as ``u2sa_hw.drivers``,
``u2sa_hw.hil``, ``u2sa_hw.mocks`` and ``u2sa_hw.simulation``) import the rest of ``u2sa_hw``; the rest
imports none of them at import time. Only a CLI command (or a check that reads the mock catalog) may
reach them, inside the function that needs them, and only the modules named in
``LAZY_BOUNDARIES`` do.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

from test_import_graph import module_level

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "u2sa_hw"
OUTSIDE = ("u2sa_hw.mocks", "u2sa_hw.hil", "u2sa_hw.drivers", "u2sa_hw.simulation")
LAZY_BOUNDARIES = {   # module -> why it may import one of OUTSIDE inside a function
    "u2sa_hw.cli.sim_cmd": "u2sa sim runs the simulation package",
    "u2sa_hw.cli.mock_cmd": "u2sa mock starts the mock devices",
    "u2sa_hw.cli.replay_cmd": "u2sa replay runs hil's replay",
    "u2sa_hw.cli.replay_check_cmd": "u2sa replay-check runs hil's replay",
    "u2sa_hw.check.device_checks": "u2sa check reads the mock catalog and [simulation] through mock_devices",
}


def _modules() -> list[tuple[str, Path]]:
    """Every module of u2sa_hw (``__main__`` left out: importing it runs the CLI)."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(REPO).with_suffix("").parts
        if "__pycache__" in parts or parts[-1] == "__main__":
            continue
        if parts[-1] == "__init__":
            parts = parts[:-1]
        found.append((".".join(parts), path))
    return found


def _outside(name: str | None) -> str | None:
    top = ".".join((name or "").split(".")[:2])
    return top if top in OUTSIDE else None


def _imported(node: ast.AST) -> list[str]:
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    if isinstance(node, ast.ImportFrom) and node.level == 0:
        return [node.module or ""]
    return []


def test_no_module_level_import_of_the_outside_packages() -> None:
    """Static: no u2sa_hw module imports drivers, hil, mock_devices or simulation at module level."""
    bad = []
    for name, path in _modules():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in module_level(tree.body):
            for target in _imported(node):
                if _outside(target):
                    bad.append(f"{path.relative_to(REPO)}:{node.lineno}: import {target}")
    assert not bad, "u2sa_hw must not import these at module level (DESIGN.md section 1):\n" + "\n".join(bad)


def test_only_the_lazy_boundaries_reach_the_outside_packages() -> None:
    """Static: an import of them anywhere in u2sa_hw (a function, TYPE_CHECKING) is in a named boundary."""
    bad = []
    for name, path in _modules():
        if name in LAZY_BOUNDARIES:
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            for target in _imported(node):
                if _outside(target):
                    bad.append(f"{path.relative_to(REPO)}:{node.lineno}: import {target}")
    assert not bad, ("these u2sa_hw modules import a package that lives outside u2sa_hw (move the module "
                     "out, e.g. to simulation/, or make it a CLI command's lazy import):\n" + "\n".join(bad))


IMPORT_EACH = """
import importlib, json, sys
outside = {outside!r}
culprits = {{}}
for name in {names!r}:
    before = {{".".join(m.split(".")[:2]) for m in sys.modules}}
    importlib.import_module(name)
    new = sorted({{".".join(m.split(".")[:2]) for m in sys.modules}} - before & set(outside))
    if new:
        culprits[name] = new
print(json.dumps(culprits))
"""


def test_importing_u2sa_hw_loads_none_of_the_outside_packages() -> None:
    """At run time, in a fresh interpreter: importing each u2sa_hw module loads none of them."""
    names = [name for name, _ in _modules()]
    code = IMPORT_EACH.format(outside=OUTSIDE, names=names)
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-4000:]
    culprits = json.loads(done.stdout.strip().splitlines()[-1])
    assert not culprits, "importing these u2sa_hw modules loaded packages outside u2sa_hw: " + \
        ", ".join(f"{name} -> {', '.join(pkgs)}" for name, pkgs in culprits.items())
