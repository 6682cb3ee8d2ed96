"""The shipped Foxglove layout shows who is driving, on topics the live bridge really advertises (issue 26).

The layout (``examples/foxglove/u2sa-layout.json``) has panels for the RC mode, armed and
``blocked_by`` (RC_MODE), the pilot's sticks (MANUAL_CMD) and the failsafe (the HSM's
``/health.failsafe`` and the FAILSAFE commands). A real ``u2sa foxglove`` process and a
real WebSocket client check that the bridge advertises those topics when the messages are
published (RC_MODE signed with the pilot key, as the RC mux signs it), and that every
message path of those panels resolves in the messages it sends, under the schema it
advertised: a renamed field or topic leaves a panel empty, and fails here.
"""

from __future__ import annotations

import asyncio
import json
import re
import tomllib
from typing import Any

import pytest
from conftest import REPO, ServiceProcesses
from test_foxglove_bridge import Client, advertised, bridge_port, start_bridge

from u2sa_hw.drivers.rc_mux.pulse import MODE_NAMES
from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t

websockets = pytest.importorskip("websockets")

LAYOUT = REPO / "examples" / "foxglove" / "u2sa-layout.json"
DRIVING_TOPICS = {"RC_MODE", "MANUAL_CMD/PercentageCommand", "FAILSAFE"}
_STEP = re.compile(r'\{([\w.]+)==(?:"([^"]*)"|([^}]*))\}|\.(\w+)|\[(\d+)\]')


def layout() -> dict[str, Any]:
    return json.loads(LAYOUT.read_text())


def panel_paths(panel: str, config: dict[str, Any]) -> list[str]:
    """Every message path (or bare topic) a panel reads, by its kind (the part of its id before ``!``)."""
    kind = panel.split("!")[0]
    if kind == "Map":
        return [config["followTopic"], *config.get("topicColors", {})]
    if kind == "3D":
        return list(config["topics"])
    if kind in ("Plot", "StateTransitions"):
        return [p["value"] for p in config["paths"]]
    if kind in ("Table", "RawMessages"):
        return [config["topicPath"]]
    if kind == "Indicator":
        return [config["path"]]
    if kind == "Log":
        return [config["topicToRender"]]
    if kind == "Parameters":
        return []
    raise AssertionError(f"panel {panel}: a kind this test does not know; teach panel_paths its paths")


def split_path(path: str) -> tuple[str, str]:
    """(topic, the rest) of a message path: the topic ends at the first ``{`` or at a ``.`` before a field name."""
    m = re.match(r"(/?[A-Za-z_][\w/]*)(.*)", path)
    assert m, path
    return m.group(1), m.group(2)


def resolve(payload: Any, rest: str) -> list[Any]:
    """The values a message path's *rest* (``{a.b=="x"}.c``, ``.d[0]``) takes in one message; [] when a filter
    leaves it out; KeyError when a field it names is not in the message."""
    values = [payload]
    pos = 0
    while pos < len(rest):
        m = _STEP.match(rest, pos)
        assert m, f"cannot read the message path {rest!r} at {rest[pos:]!r}"
        pos = m.end()
        field_path, quoted, bare, name, index = m.groups()
        if field_path is not None:
            want = quoted if quoted is not None else json.loads(bare)
            values = [v for v in values if resolve(v, "." + field_path) == [want]]
        elif name is not None:
            values = [v[name] for v in values]   # KeyError: the message has no such field
        else:
            values = [v[int(index)] for v in values]
    return values


def schema_has(schema: dict[str, Any], rest: str) -> bool:
    """Whether the advertised JSON Schema declares every field *rest* names (filters included)."""
    node = schema
    for field_path, _q, _b, name, index in (m.groups() for m in _STEP.finditer(rest)):
        if field_path is not None:
            if not schema_has(node, "." + field_path):
                return False
            continue
        if index is not None:
            node = node.get("items", {})
            continue
        props = node.get("properties", {})
        if name not in props:
            return False
        node = props[name]
    return True


def driving_panels(config_by_id: dict[str, Any]) -> dict[str, list[str]]:
    """The panels reading RC_MODE, MANUAL_CMD, FAILSAFE or the HSM's failsafe flag, with their paths."""
    out = {}
    for panel, config in config_by_id.items():
        paths = panel_paths(panel, config)
        if any(split_path(p)[0] in DRIVING_TOPICS or p == "/health.failsafe" for p in paths):
            out[panel] = paths
    return out


def leaves(node: Any) -> list[str]:
    return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])


def test_the_layout_has_panels_for_the_mode_armed_blocked_by_sticks_and_failsafe() -> None:
    lay = layout()
    configs = lay["configById"]
    shown = leaves(lay["layout"])
    assert sorted(shown) == sorted(configs), "every panel configured is placed once in the layout, and only those"
    panels = driving_panels(configs)
    by_path: dict[str, set[str]] = {}
    for panel, paths in panels.items():
        for p in paths:
            by_path.setdefault(p, set()).add(panel.split("!")[0])
    assert "Indicator" in by_path["RC_MODE.mode_name"] and "Indicator" in by_path["RC_MODE.armed"]
    assert "Indicator" in by_path["RC_MODE.autonomy_enabled"]
    assert by_path["RC_MODE.blocked_by"] == {"StateTransitions"} and "RawMessages" in by_path["RC_MODE"]
    assert "RawMessages" in by_path["FAILSAFE"] and "StateTransitions" in by_path["FAILSAFE.active"]
    assert by_path["/health.failsafe"] >= {"Indicator"}   # held by any source, as the HSM sees it
    # The mode indicator's rules are the words the RC mux sends, and each boolean rule is a JSON boolean.
    mode_rules = {r["rawValue"] for r in configs["Indicator!rc_mode"]["rules"]}
    assert mode_rules == set(MODE_NAMES.values())
    for panel in ("Indicator!autonomy", "Indicator!armed", "Indicator!failsafe"):
        assert {r["rawValue"] for r in configs[panel]["rules"]} == {"true", "false"}, panel
    # The sticks plot has a series for every output of every example's manual mixer.
    sticks = {m.group(1) for p in configs["Plot!sticks"]["paths"]
              for m in [re.search(r'actuator_name=="(\w+)"', p["value"])] if m}
    mixed = set()
    for profile in sorted((REPO / "examples").glob("*/vehicle.toml")):
        mixer = tomllib.loads(profile.read_text()).get("safety", {}).get("manual_mixer", {})
        mixed |= {mixer[k] for k in ("left", "right") if k in mixer}
    assert mixed and mixed <= sticks, f"outputs of the examples' manual mixers without a series: {mixed - sticks}"


def test_the_path_reader_refuses_a_field_the_message_lacks() -> None:
    msg = {"base": {"actuator_name": "left_wheel"}, "percentage": 12.5}
    assert resolve(msg, '{base.actuator_name=="left_wheel"}.percentage') == [12.5]
    assert resolve(msg, '{base.actuator_name=="right_wheel"}.percentage') == []
    with pytest.raises(KeyError):
        resolve(msg, ".percent")
    schema = {"properties": {"base": {"properties": {"actuator_name": {}}}, "percentage": {}}}
    assert schema_has(schema, '{base.actuator_name=="x"}.percentage') and not schema_has(schema, ".percent")


@pytest.mark.timeout(120)
def test_the_bridge_advertises_what_the_driving_panels_read(services: ServiceProcesses, bus: Any) -> None:
    panels = driving_panels(layout()["configById"])
    paths = sorted({p for ps in panels.values() for p in ps})
    topics = {split_path(p)[0] for p in paths}
    assert DRIVING_TOPICS | {"/health"} == topics
    proc, err = start_bridge(services)
    port = bridge_port(proc, err)
    sticks = sorted({m.group(1) for p in paths for m in [re.search(r'actuator_name=="(\w+)"', p)] if m})

    mode = t.RcMode()
    mode.mode, mode.mode_name, mode.armed, mode.autonomy_enabled = 1, MODE_NAMES[1], True, False
    mode.blocked_by, mode.header.source = "pre-arm check failed: gps: no 3D fix", "rc"
    failsafe = t.Failsafe()
    failsafe.active, failsafe.reason, failsafe.header.source = True, "required service gps failed", "hsm"
    system = t.SystemHealth()
    system.failsafe, system.summary = True, "FAILSAFE held by hsm"

    def publish() -> None:
        assert bus.publish(ch.RC_MODE, mode)   # signed with the session's pilot key, as the mux signs it
        for i, name in enumerate(sticks):
            cmd = t.PercentageCommand()
            cmd.base.actuator_name, cmd.percentage = name, 10.0 * (i + 1)
            assert bus.publish(ch.MANUAL_CMD, cmd)
        assert bus.publish(ch.FAILSAFE, failsafe)
        assert bus.publish(ch.SYSTEM_HEALTH, system)

    ids = {topic: i + 1 for i, topic in enumerate(sorted(topics))}
    c: Client | None = None

    def got(topic: str) -> list[dict[str, Any]]:
        assert c is not None
        return [p for _ts, p in c.data.get(ids[topic], [])]

    def every_stick_seen() -> bool:
        names = {p["base"]["actuator_name"] for p in got("MANUAL_CMD/PercentageCommand")}
        return set(sticks) <= names and all(got(topic) for topic in topics)

    async def session() -> Client:
        nonlocal c
        async with advertised(port, topics, tick=publish) as client:
            c = client
            await client.subscribe({i: topic for topic, i in ids.items()})
            await client.pump(every_stick_seen, timeout=60, tick=publish)
            return client

    try:
        c = asyncio.run(session())
    except BaseException:
        print(f"the bridge's stderr:\n{err.read_text()}\nstatus messages: {c.status if c else None}")
        raise
    assert c.channels["RC_MODE"]["schemaName"] == "u2sa.RcMode"
    assert c.channels["FAILSAFE"]["schemaName"] == "u2sa.Failsafe"
    for path in paths:
        topic, rest = split_path(path)
        schema = json.loads(c.channels[topic]["schema"])
        assert schema_has(schema, rest), f"{path}: the schema the bridge advertised for {topic} lacks a field"
        values = [v for p in c.validated(ids[topic], topic) for v in resolve(p, rest)]
        assert values, f"{path}: no message the bridge sent has it"
        if rest:   # a field, not a whole message: Plot, Indicator and State Transitions read a single value
            assert all(isinstance(v, (bool, int, float, str)) for v in values), (path, values[:3])
    latest = {topic: got(topic)[-1] for topic in topics}
    assert latest["RC_MODE"]["blocked_by"] == "pre-arm check failed: gps: no 3D fix"
    assert latest["RC_MODE"]["mode_name"] == "autonomous" and latest["/health"]["failsafe"] is True
    assert latest["FAILSAFE"]["reason"] == "required service gps failed"
