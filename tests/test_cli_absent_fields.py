"""A field its presence vector leaves out is shown as absent, never as 0.0 (issue 26).

An IMU-like StateInformation that carries no heading: ``u2sa echo`` and ``u2sa log echo``
print ``psi: -`` in text and ``"psi": null`` with --json; ``u2sa log export --foxglove``
writes null (its schema allows it). Present fields keep their values, a present 0.0 stays 0.0.
Real processes on a private bus and a log written by the recorder's writer.
"""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path
from typing import Iterator

import pytest
from conftest import U2SA
from mcap.reader import make_reader

from u2sa_hw import lcmtypes as t
from u2sa_hw.recording.mcap_log import McapLogWriter, RunInfo

# pitch rate present and exactly 0.0; heading (psi), position and every other field absent
FIELDS = {"phi": 0.25, "theta": -0.5, "theta_dot": 0.0, "psi_dot": 0.125}


def imu_message() -> t.StateInformation:
    msg = t.StateInformation().set(**FIELDS)
    msg.sensor_name, msg.reference_frame = "imu", "BODY"
    return msg


def text_fields(stdout: str) -> dict[str, str]:
    """The ``name: value`` lines of the first message printed in text."""
    block = stdout.split("--- ")[1]
    pairs = (line.strip().partition(":") for line in block.splitlines()[1:])
    return {name: value.strip() for name, _sep, value in pairs}


def assert_absent_shown_as_absent(fields: dict, *, absent: object) -> None:
    for name, value in FIELDS.items():
        assert float(fields[name]) == value, (name, fields[name])
    for name in ("psi", "x", "y", "psi_sigma", "fluid_z_ddot_sigma"):
        assert fields[name] == absent, (name, fields[name])


@pytest.fixture
def imu_publisher(lcm_url: str, tmp_path: Path) -> Iterator[None]:
    fields = [f"{k}={v}" for k, v in FIELDS.items()]
    proc = subprocess.Popen([*U2SA, "pub", "STATE_INFO", "StateInformation", "sensor_name=imu", *fields,
                             "--rate", "20"], cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    yield
    proc.terminate()
    proc.wait(timeout=10)


def test_echo_shows_an_absent_field_as_dash_and_null(imu_publisher: None, tmp_path: Path) -> None:
    text = subprocess.run([*U2SA, "echo", "STATE_INFO", "--count", "1", "--wait"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=60)
    assert text.returncode == 0, text.stderr
    assert_absent_shown_as_absent(text_fields(text.stdout), absent="-")
    js = subprocess.run([*U2SA, "echo", "STATE_INFO", "--count", "1", "--wait", "--json"], cwd=tmp_path,
                        capture_output=True, text=True, timeout=60)
    assert js.returncode == 0, js.stderr
    assert_absent_shown_as_absent(json.loads(js.stdout.splitlines()[0]), absent=None)


@pytest.fixture
def imu_log(tmp_path: Path) -> Path:
    path = tmp_path / "imu.mcap"
    writer = McapLogWriter(tmp_path, path=path, run=RunInfo(vehicle="rover"))
    writer.write("STATE_INFO", imu_message().encode(), time.time_ns())
    writer.close()
    return path


def test_log_echo_shows_an_absent_field_as_dash_and_null(imu_log: Path, tmp_path: Path) -> None:
    text = subprocess.run([*U2SA, "log", "echo", str(imu_log), "STATE_INFO"], cwd=tmp_path, capture_output=True,
                          text=True, timeout=60)
    assert text.returncode == 0, text.stderr
    assert_absent_shown_as_absent(text_fields(text.stdout), absent="-")
    js = subprocess.run([*U2SA, "log", "echo", str(imu_log), "STATE_INFO", "--json"], cwd=tmp_path,
                        capture_output=True, text=True, timeout=60)
    assert js.returncode == 0, js.stderr
    assert_absent_shown_as_absent(json.loads(js.stdout.splitlines()[0]), absent=None)


def test_foxglove_export_writes_an_absent_field_as_null(imu_log: Path, tmp_path: Path) -> None:
    jsonschema = pytest.importorskip("jsonschema")
    out = tmp_path / "fox.mcap"
    done = subprocess.run([*U2SA, "log", "export", str(imu_log), "--foxglove", str(out)], cwd=tmp_path,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    with open(out, "rb") as fh:
        found = [(json.loads(s.data), json.loads(m.data)) for s, c, m in make_reader(fh).iter_messages()
                 if c.topic == "STATE_INFO"]
    assert len(found) == 1
    schema, payload = found[0]
    jsonschema.validate(payload, schema)
    assert_absent_shown_as_absent(payload, absent=None)
