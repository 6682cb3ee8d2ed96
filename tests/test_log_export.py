"""Foxglove export and plots of a log written by the recorder's writer: every exported message is valid
against its own schema, one schema per (channel, type), with the well-known messages the live bridge sends."""

from __future__ import annotations

import json
import math
import re
import time
from pathlib import Path

import jsonschema
import pytest
from conftest import REPO
from mcap.reader import make_reader
from recorded_sim import recorded_sim

from u2sa_hw import lcmtypes as t
from u2sa_hw.recording.foxglove import export_foxglove
from u2sa_hw.recording.mcap_log import McapLogWriter, RunInfo
from u2sa_hw.recording.plot import plot_log

PROFILE = b'[vehicle]\nname = "rover"\norigin = { lat = 29.19, lon = -81.05, alt = 10.0 }\n'


@pytest.fixture
def log_path(tmp_path: Path) -> Path:
    path = tmp_path / "run.mcap"
    writer = McapLogWriter(tmp_path, path=path, run=RunInfo(vehicle="rover", attachments={"vehicle.toml": PROFILE}))
    t0 = time.time_ns()
    for i in range(40):
        s = t.StateInformation().set(x=i * 0.5, y=math.sin(i / 5), psi=0.1 * i, x_dot=1.0, y_dot=0.1,
                                     x_sigma=0.5, y_sigma=0.5)
        s.sensor_name, s.reference_frame = "state_estimator", "NED"
        writer.write("STATE_ESTIMATE", s.encode(), t0 + i * 50_000_000)
        cmd = t.PercentageCommand()
        cmd.base.actuator_name, cmd.percentage = "left", 10.0 + i
        writer.write("ACTUATOR_CMD", cmd.encode(), t0 + i * 50_000_000 + 1000)
    gps = t.StateInformation().set(x=29.1901, y=-81.0501)
    gps.sensor_name, gps.reference_frame = "gps", "GEODETIC"
    writer.write("STATE_INFO", gps.encode(), t0 + 10)
    writer.write("STATE_INFO", b"\x00\x01garbage", t0 + 20)  # undecodable: skipped, not fatal
    writer.close()
    return path


def test_export_reads_back_and_validates_against_its_schemas(log_path: Path, tmp_path: Path) -> None:
    out = tmp_path / "fox.mcap"
    counts = export_foxglove(log_path, out).counts
    assert counts["STATE_ESTIMATE"] == 40 and counts["/location/STATE_ESTIMATE"] == 40
    assert counts["/location/STATE_INFO"] == 1 and counts["ACTUATOR_CMD/PercentageCommand"] == 40
    assert counts["/tf"] == 40 and counts["/pose"] == 40
    seen = 0
    with open(out, "rb") as fh:
        reader = make_reader(fh)
        for schema, channel, message in reader.iter_messages():
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            payload = json.loads(message.data)
            jsonschema.validate(payload, json.loads(schema.data))
            seen += 1
            if channel.topic == "/location/STATE_INFO":
                assert schema.name == "foxglove.LocationFix"
                assert payload["latitude"] == pytest.approx(29.1901) and payload["longitude"] == pytest.approx(-81.0501)
            if channel.topic == "/location/STATE_ESTIMATE" and payload["frame_id"] == "state_estimator":
                assert 29.18 < payload["latitude"] < 29.20 and payload["position_covariance_type"] == 2
    assert seen == sum(counts.values())


def test_schema_rejects_a_wrong_payload(log_path: Path, tmp_path: Path) -> None:
    out = tmp_path / "fox.mcap"
    export_foxglove(log_path, out)
    with open(out, "rb") as fh:
        schema = next(s for s, c, _m in make_reader(fh).iter_messages() if c.topic == "ACTUATOR_CMD/PercentageCommand")
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({"_type": "PercentageCommand", "base": {}, "percentage": "fast"}, json.loads(schema.data))


def test_plot_writes_a_png(log_path: Path, tmp_path: Path) -> None:
    png = tmp_path / "run.png"
    counts = plot_log(log_path, png)
    assert counts["track"] == 40 and counts["commands"] == 40
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_nan_and_infinite_fields_export_as_null_and_still_validate(tmp_path: Path) -> None:
    path = tmp_path / "nan.mcap"
    writer = McapLogWriter(tmp_path, path=path, run=RunInfo(vehicle="rover", attachments={"vehicle.toml": PROFILE}))
    t0 = time.time_ns()
    good = t.StateInformation().set(x=1.0, y=2.0, psi=float("nan"), x_sigma=float("inf"), y_sigma=0.5)
    good.sensor_name, good.reference_frame = "estimator", "NED"
    writer.write("STATE_ESTIMATE", good.encode(), t0)
    lost = t.StateInformation().set(x=float("nan"), y=2.0)   # no position: no LocationFix
    lost.sensor_name, lost.reference_frame = "estimator", "NED"
    writer.write("STATE_ESTIMATE", lost.encode(), t0 + 1000)
    writer.close()
    out = tmp_path / "fox.mcap"
    counts = export_foxglove(path, out).counts
    assert counts == {"STATE_ESTIMATE": 2, "/location/STATE_ESTIMATE": 1}   # a NaN heading gives no /tf
    payloads = {}
    with open(out, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages():
            payload = json.loads(message.data)
            jsonschema.validate(payload, json.loads(schema.data))
            payloads.setdefault(channel.topic, []).append(payload)
    first = payloads["STATE_ESTIMATE"][0]
    assert first["psi"] is None and first["x_sigma"] is None and first["y_sigma"] == 0.5
    assert payloads["STATE_ESTIMATE"][1]["x"] is None
    fix = payloads["/location/STATE_ESTIMATE"][0]
    assert fix["position_covariance_type"] == 0 and all(math.isfinite(v) for v in fix["position_covariance"])


def _validated(out: Path) -> dict[str, list[tuple[str, dict]]]:
    """Every message of a Foxglove export, checked against its own channel's schema: topic -> [(schema, payload)]."""
    by_topic: dict[str, list[tuple[str, dict]]] = {}
    validators: dict[int, jsonschema.Draft202012Validator] = {}
    with open(out, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages():
            v = validators.get(schema.id)
            if v is None:
                v = validators[schema.id] = jsonschema.Draft202012Validator(json.loads(schema.data))
            payload = json.loads(message.data)
            errors = [e.message for e in v.iter_errors(payload)]
            assert not errors, f"{channel.topic} ({schema.name}): {errors[:3]}"
            by_topic.setdefault(channel.topic, []).append((schema.name, payload))
    return by_topic


def _shape(cls: type, uid: str, **fields: float) -> object:
    msg = cls()
    base = msg.base.base
    base.uid, base.reference_frame, base.x, base.y, base.object_type = uid, "NED", 10.0, 5.0, "obstacle"
    for name, value in fields.items():
        setattr(msg, name, value)
    return msg


def test_mixed_channels_get_one_schema_per_type_and_the_scene(tmp_path: Path) -> None:
    path = tmp_path / "mixed.mcap"
    writer = McapLogWriter(tmp_path, path=path, run=RunInfo(vehicle="rover", attachments={"vehicle.toml": PROFILE}))
    t0 = time.time_ns()
    for i in range(6):   # RAW.rc carries edges and writes, interleaved
        edge = t.RawGpioEdge()
        edge.device, edge.line, edge.edge, edge.kernel_timestamp_ns = "rc", 3, 1, t0 + i
        writer.write("RAW.rc", edge.encode(), t0 + 10 * i)
        if i % 3 == 0:
            w = t.RawGpioWrite()
            w.device, w.line, w.value = "rc", 7, 1
            writer.write("RAW.rc", w.encode(), t0 + 10 * i + 1)
    poly = _shape(t.Polygon, "pier", num_vertices=3)
    poly.vx, poly.vy = [0.0, 4.0, 4.0], [0.0, 0.0, 3.0]
    world = [_shape(t.Circle, "buoy", radius=1.5), _shape(t.Rectangle, "dock", length=4.0, width=2.0, heading=0.5),
             poly]
    for i, obj in enumerate(world):
        writer.write("WORLD", obj.encode(), t0 + 100 + i)
    summary = t.WorldSummary()
    summary.uids, summary.num_objects = ["buoy", "dock"], 2   # the pier is gone
    writer.write("WORLD_SUMMARY", summary.encode(), t0 + 200)
    wp = t.Waypoint()
    wp.base.uid, wp.reference_frame, wp.x, wp.y, wp.horizontal_threshold = "wp1", "LOCAL", 20.0, 3.0, 2.0
    writer.write("GOALS", wp.encode(), t0 + 300)
    nav = t.NavigationPoint()
    nav.goal_uid, nav.x, nav.y, nav.speed, nav.distance_to_goal = "wp1", 19.0, 3.0, 1.2, 7.5
    writer.write("NAV_POINT", nav.encode(), t0 + 400)
    health = t.Health()
    health.name, health.status, health.uptime_s = "gps", "ok", 5.0
    writer.write("U2SA_HEALTH", health.encode(), t0 + 500)
    sysh = t.SystemHealth()
    state = t.ServiceState()
    state.name, state.state, state.last_error, state.heartbeat_age_s = "gps", "degraded", "no fix", 0.4
    sysh.services, sysh.num_services, sysh.summary = [state], 1, "1 degraded"
    writer.write("U2SA_SYSTEM_HEALTH", sysh.encode(), t0 + 600)
    writer.close()
    logs = tmp_path / "logs"
    logs.mkdir()
    stamp = time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(t0 / 1e9))
    (logs / "gps.log").write_text(f"{stamp}.123 WARN  gps [1] no fix yet\n{stamp}.456 ERROR gps [1] port lost\n"
                                  "Traceback (most recent call last):\n  boom\n"
                                  "2001-01-01T00:00:00.000 INFO  gps [1] another run's line\n")
    out = tmp_path / "fox.mcap"
    report = export_foxglove(path, out, log_dir=logs)
    topics = _validated(out)
    edges, writes = topics["RAW.rc/RawGpioEdge"], topics["RAW.rc/RawGpioWrite"]
    assert {s for s, _ in edges} == {"u2sa.RawGpioEdge"} and len(edges) == 6
    assert {s for s, _ in writes} == {"u2sa.RawGpioWrite"} and len(writes) == 2
    assert {"WORLD/Circle", "WORLD/Rectangle", "WORLD/Polygon"} <= set(topics)
    scene = [p for _s, p in topics["/scene/world"]]
    kinds = {e["id"]: [k for k in ("cylinders", "cubes", "lines") if e[k]] for p in scene for e in p["entities"]}
    assert kinds == {"object/buoy": ["cylinders"], "object/dock": ["cubes"], "object/pier": ["lines"]}
    assert [d["id"] for p in scene for d in p["deletions"]] == ["object/pier"]
    (mission,) = [p for _s, p in topics["/scene/mission"]]
    wp_entity = mission["entities"][0]
    assert wp_entity["id"] == "waypoint/wp1" and wp_entity["spheres"][0]["pose"]["position"]["x"] == 3.0  # east
    assert wp_entity["lines"] and wp_entity["lines"][0]["type"] == 1   # the threshold circle
    assert topics["/scene/nav"][0][1]["entities"][0]["id"] == "nav_point"
    (row,) = topics["/health"][0][1]["services"]
    assert row["name"] == "gps" and row["state"] == "degraded" and row["reason"] == "no fix" and row["status"] == "ok"
    lines = [p for _s, p in topics["/log"]]
    assert [(p["name"], p["level"]) for p in lines] == [("gps", 3), ("gps", 4)]   # another run's line left out
    assert "Traceback" in lines[1]["message"]
    assert report.undecodable == 0


def test_without_an_origin_the_export_says_why_there_is_no_map(tmp_path: Path) -> None:
    path = tmp_path / "bare.mcap"
    writer = McapLogWriter(tmp_path, path=path, run=RunInfo(vehicle=""))   # u2sa record without --vehicle
    s = t.StateInformation().set(x=1.0, y=2.0, psi=0.1)
    s.sensor_name, s.reference_frame = "state_estimator", "NED"
    writer.write("STATE_ESTIMATE", s.encode(), time.time_ns())
    writer.close()
    report = export_foxglove(path, tmp_path / "fox.mcap")
    assert "/location/STATE_ESTIMATE" not in report.counts and report.counts["/tf"] == 1
    assert "recorded without --vehicle" in report.notes[0]


def _layout_topics() -> set[str]:
    """Every topic the shipped Foxglove layout reads."""
    layout = json.loads((REPO / "examples" / "foxglove" / "u2sa-layout.json").read_text())
    topics: set[str] = set()
    for panel, config in layout["configById"].items():
        kind = panel.split("!")[0]
        if kind == "Map":
            topics.add(config["followTopic"])
        elif kind == "3D":
            topics.update(config["topics"])
        elif kind == "Plot":
            topics.update(re.split(r"[.{]", p["value"], maxsplit=1)[0] for p in config["paths"])
        elif kind == "Table":
            topics.add(config["topicPath"].split(".")[0])
        elif kind == "Log":
            topics.add(config["topicToRender"])
    return topics


@pytest.mark.timeout(300)
def test_every_message_of_a_recorded_simulation_is_valid_and_the_layout_finds_its_topics(
        tmp_path_factory: pytest.TempPathFactory, tmp_path: Path) -> None:
    sim = recorded_sim(tmp_path_factory)
    out = tmp_path / "fox.mcap"
    report = export_foxglove(sim.log, out, log_dir=sim.logs)
    topics = _validated(out)
    assert sum(len(v) for v in topics.values()) == sum(report.counts.values())
    assert {"RAW.rc/RawGpioEdge", "/location/STATE_ESTIMATE", "/location/STATE_INFO", "/tf", "/scene/world",
            "/scene/mission", "/log", "/health"} <= set(topics)
    missing = _layout_topics() - set(topics)
    assert not missing, f"the layout reads topics the export of the example rover lacks: {missing}"
    assert report.notes == [] and report.undecodable == 0
