"""The layers and the one direction of imports (issue 25 item 6; docs/architecture.md).

Every module of the installed code belongs to one layer of :data:`LAYERS` (the longest prefix
wins), and a module-level import never reaches a higher layer than its own. Imports inside a
function are the lazy boundaries tests/test_layout.py names; they are not counted here. The graph
is tests/test_import_graph.py's (module level, ``TYPE_CHECKING`` left out)."""

from __future__ import annotations

from test_import_graph import import_graph

#: bottom to top; docs/architecture.md draws the same table
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("foundation", ("u2sa_hw", "u2sa_hw.messages", "u2sa_hw.lcmtypes", "u2sa_hw.channels", "u2sa_hw.geo",
                    "u2sa_hw.protocols", "u2sa_hw.registry", "u2sa_hw.realtime", "u2sa_hw.failsafe",
                    "u2sa_hw.geofence", "u2sa_hw.message_codegen", "u2sa_hw.message_presence_gen")),
    ("ports", ("u2sa_hw.ports",)),
    ("bus", ("u2sa_hw.bus",)),
    ("config", ("u2sa_hw.config",)),
    ("profile", ("u2sa_hw.profile", "u2sa_hw.geofence_parse", "u2sa_hw.geofence_draw")),
    ("service", ("u2sa_hw.service",)),
    ("safety", ("u2sa_hw.safety",)),
    ("abstract", ("u2sa_hw.abstract",)),
    ("applications", ("u2sa_hw.services", "u2sa_hw.recording", "u2sa_hw.foxglove", "u2sa_hw.launcher",
                      "u2sa_hw.install", "u2sa_hw.check", "u2sa_hw.calibration",
                      # reads a whole vehicle.toml against every layer's rules (kinds, safety, supervision)
                      "u2sa_hw.profile.loader")),
    ("cli", ("u2sa_hw.cli",)),
    ("devices, mocks, replay, simulation", ("u2sa_hw.drivers", "u2sa_hw.mocks", "u2sa_hw.hil", "u2sa_hw.simulation")),
]


def layer_of(module: str) -> int | None:
    """The index in :data:`LAYERS` of *module* (longest matching prefix), or None outside them all."""
    best: tuple[int, int] | None = None
    for index, (_name, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and (best is None or len(prefix) > best[1]):
                best = (index, len(prefix))
    return best[0] if best else None


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    """Each import of *graph* from a module into a higher layer than its own, as a line."""
    found = []
    for module, targets in sorted(graph.items()):
        own = layer_of(module)
        for target in sorted(targets):
            theirs = layer_of(target)
            if own is not None and theirs is not None and theirs > own:
                found.append(f"{module} ({LAYERS[own][0]}) imports {target} ({LAYERS[theirs][0]})")
    return found


def test_the_layer_table_finds_an_upward_import() -> None:
    graph = {"u2sa_hw.bus.transport": {"u2sa_hw.service.health", "u2sa_hw.messages"},
             "u2sa_hw.service.contract": {"u2sa_hw.bus.transport"},
             "u2sa_hw.profile.loader": {"u2sa_hw.services.hsm.rules"}}
    assert upward_imports(graph) == ["u2sa_hw.bus.transport (bus) imports u2sa_hw.service.health (service)"]
    assert layer_of("u2sa_hw.profile.loader") > layer_of("u2sa_hw.safety.prearm") > layer_of("u2sa_hw.profile.vehicle")


def test_every_module_has_a_layer() -> None:
    graph = import_graph()
    assert graph and not [m for m in graph if layer_of(m) is None]


def test_no_module_imports_a_higher_layer() -> None:
    bad = upward_imports(import_graph())
    assert not bad, ("these imports go up the layers of docs/architecture.md (move the shared piece down, "
                     "or the importing module up):\n" + "\n".join(bad))
