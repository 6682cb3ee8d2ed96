"""Foxglove export and plots of a log written by the recorder's writer."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import jsonschema
import pytest
from mcap.reader import make_reader

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
    counts = export_foxglove(log_path, out)
    assert counts["STATE_ESTIMATE"] == 40 and counts["/location/STATE_ESTIMATE"] == 40
    assert counts["/location/STATE_INFO"] == 1 and counts["ACTUATOR_CMD"] == 40
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
        schema = next(s for s, c, _m in make_reader(fh).iter_messages() if c.topic == "ACTUATOR_CMD")
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
    counts = export_foxglove(path, out)
    assert counts == {"STATE_ESTIMATE": 2, "/location/STATE_ESTIMATE": 1}
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
