"""No import circles (issue 25, item 5): the module-level imports of the installed code form no cycle.

A cycle makes a module's import order matter (half-initialised modules, names missing at import)
and ties the modules on it into one lump that cannot be read or moved alone. The graph is built
statically with ``ast`` from every module of ``u2sa_hw`` and of the folders that install inside it
(``drivers/`` as ``u2sa_hw.drivers``, ``mock_devices/`` as ``u2sa_hw.mocks``, ``hil/`` as
``u2sa_hw.hil``, ``simulation/`` as ``u2sa_hw.simulation``; setup.py's package-dir). Only the
imports run at import time count: the top level and top-level ``if``/``try``/``with`` blocks, not
functions and not ``if TYPE_CHECKING:``. ``from pkg import name`` counts as importing the submodule
``pkg.name`` when there is one, else ``pkg``. A cycle is a strongly connected component of more than
one module, or a module importing itself; the fix is to move the shared piece down into a module
that both import, not to hide an import inside a function.
"""

from __future__ import annotations

import ast
from collections.abc import Iterable, Mapping
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: folder -> the dotted name it installs as (setup.py's package-dir, plus the package itself)
ROOTS = {
    "u2sa_hw": "u2sa_hw",
    "drivers": "u2sa_hw.drivers",
    "mock_devices": "u2sa_hw.mocks",
    "hil": "u2sa_hw.hil",
    "simulation": "u2sa_hw.simulation",
}


def installed_modules() -> dict[str, tuple[Path, bool]]:
    """Every module's installed dotted name -> (its file, whether it is a package's ``__init__``)."""
    found: dict[str, tuple[Path, bool]] = {}
    for folder, dotted in ROOTS.items():
        base = REPO / folder
        for path in sorted(base.rglob("*.py")):
            parts = path.relative_to(base).with_suffix("").parts
            if "__pycache__" in parts or parts[-1] == "__main__":
                continue
            package = parts[-1] == "__init__"
            name = ".".join((dotted, *(parts[:-1] if package else parts)))
            found[name] = (path, package)
    return found


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or \
        (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def module_level(body: list[ast.stmt]) -> list[ast.stmt]:
    """The statements run at import: the top level and inside top-level if/try/with (not TYPE_CHECKING)."""
    out: list[ast.stmt] = []
    for node in body:
        out.append(node)
        if isinstance(node, ast.If):
            if not _is_type_checking(node):
                out += module_level(node.body)
            out += module_level(node.orelse)
        elif isinstance(node, ast.Try):
            out += module_level(node.body)
            for handler in node.handlers:
                out += module_level(handler.body)
            out += module_level(node.orelse) + module_level(node.finalbody)
        elif isinstance(node, (ast.With, ast.For, ast.While)):
            out += module_level(node.body)
    return out


def _known(name: str, modules: Iterable[str]) -> str | None:
    """``name`` itself if it is a module, else its longest prefix that is one (None: not ours)."""
    known = set(modules)
    parts = name.split(".")
    for end in range(len(parts), 0, -1):
        candidate = ".".join(parts[:end])
        if candidate in known:
            return candidate
    return None


def imports_of(name: str, path: Path, package: bool, modules: Mapping[str, object]) -> set[str]:
    """The modules among ``modules`` that ``name`` (at ``path``) imports at module level."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    here = name if package else name.rpartition(".")[0]
    targets: set[str] = set()
    for node in module_level(tree.body):
        if isinstance(node, ast.Import):
            for alias in node.names:
                targets.add(alias.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = here.split(".")
                base_parts = base_parts[:len(base_parts) - (node.level - 1)]
                base = ".".join(base_parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                targets.add(sub if sub in modules else base)
    resolved = {_known(target, modules) for target in targets}
    return {target for target in resolved if target and target != name}


def import_graph() -> dict[str, set[str]]:
    """Module -> the modules it imports at module level, over everything that installs as u2sa_hw."""
    modules = installed_modules()
    return {name: imports_of(name, path, package, modules) for name, (path, package) in modules.items()}


def cycles(graph: Mapping[str, Iterable[str]]) -> list[list[str]]:
    """The strongly connected components of ``graph`` that are cycles (Tarjan's algorithm, iterative).

    Each is sorted; a component of one node counts only when the node has an edge to itself. Edges to
    nodes outside ``graph`` are ignored.
    """
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    found: list[list[str]] = []
    edges = {node: sorted(t for t in targets if t in graph) for node, targets in graph.items()}
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work: list[tuple[str, int]] = [(root, 0)]
        while work:
            node, position = work.pop()
            if position == 0:
                index[node] = low[node] = counter
                counter += 1
                stack.append(node)
                on_stack.add(node)
            targets = edges[node]
            if position < len(targets):
                work.append((node, position + 1))
                target = targets[position]
                if target not in index:
                    work.append((target, 0))
                elif target in on_stack:
                    low[node] = min(low[node], index[target])
                continue
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1 or node in edges[node]:
                    found.append(sorted(component))
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
    return sorted(found)


def test_the_cycle_finder_finds_cycles_and_only_cycles() -> None:
    """The finder on a small graph: two cycles (one through three nodes), a self-import, and a DAG part."""
    graph = {
        "a": {"b"}, "b": {"c"}, "c": {"a", "d"},   # a -> b -> c -> a
        "d": {"e"}, "e": set(),                    # no cycle, reached from one
        "f": {"g", "outside"}, "g": {"f"},         # f <-> g, an edge out of the graph ignored
        "h": {"h"},                                # imports itself
        "i": {"d", "e"},                           # a diamond, no cycle
    }
    assert cycles(graph) == [["a", "b", "c"], ["f", "g"], ["h"]]
    assert cycles({"x": {"y"}, "y": {"z"}, "z": set()}) == []


def test_the_cycle_finder_handles_a_long_chain_without_recursion() -> None:
    """Iterative, so a deep import chain does not hit Python's recursion limit."""
    chain = {str(n): {str(n + 1)} for n in range(5000)}
    chain["5000"] = {"0"}
    assert cycles(chain) == [sorted(chain)]


def test_the_graph_resolves_submodules_and_relative_imports(tmp_path: Path) -> None:
    """``from pkg import mod`` is an edge to the submodule; ``from . import x`` resolves in the package."""
    (tmp_path / "one.py").write_text("from pkg import two\nfrom pkg.three import NAME\n"
                                     "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import pkg.four\n")
    (tmp_path / "rel.py").write_text("from . import two\nfrom .three import NAME\n")
    modules = {"pkg": None, "pkg.one": None, "pkg.two": None, "pkg.three": None, "pkg.four": None, "pkg.rel": None}
    assert imports_of("pkg.one", tmp_path / "one.py", False, modules) == {"pkg.two", "pkg.three"}
    assert imports_of("pkg.rel", tmp_path / "rel.py", False, modules) == {"pkg.two", "pkg.three"}


def test_the_graph_covers_the_folders_that_install_inside_u2sa_hw() -> None:
    """The mapped names are the installed ones (a renamed folder would silently drop out of the check)."""
    modules = installed_modules()
    for dotted in ROOTS.values():
        assert dotted in modules, f"no package {dotted}: ROOTS no longer matches setup.py"
    assert not any(name.startswith(("u2sa_hw.u2sa_hw", "drivers.", "hil.")) for name in modules)


def test_no_import_circles() -> None:
    """Static: the module-level import graph of u2sa_hw (and drivers, mocks, hil, simulation) has no cycle."""
    found = cycles(import_graph())
    assert not found, "module-level import circles (move the shared piece into a module both import):\n" + \
        "\n".join("  " + " <-> ".join(component) for component in found)
