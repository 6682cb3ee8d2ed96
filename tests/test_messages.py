"""Message types: presence vectors, field enumeration, the registry and extension decoding."""

from __future__ import annotations

import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from u2sa_hw import message_codegen
from u2sa_hw import messages as m


def test_state_information_has_every_figure6_field_and_setters_keep_presence() -> None:
    assert len(m.STATE_FIELDS) == 48
    s = m.StateInformation()
    assert s.present_fields() == []
    s.set(x=1.0, psi=0.5)
    s.set_fluid_z_ddot_sigma(0.1)
    assert s.presence_vector & 1  # x is bit 0, as the thesis says
    assert s.has("psi") and not s.has("y")
    assert s.get("y") is None and s.get("psi") == 0.5
    with pytest.raises(m.AbsentField):
        s.require("theta")
    assert s.present_fields() == ["x", "psi", "fluid_z_ddot_sigma"]
    s.clear("psi")
    assert not s.has("psi")
    with pytest.raises(AttributeError):
        s.set(sensor_name="no")  # not an optional field


def test_round_trip_keeps_presence_and_values() -> None:
    s = m.StateInformation().set(x_dot=2.5, theta=-0.1)
    s.sensor_name = "imu"
    d = m.StateInformation.decode(m.serialize(s))
    assert d.present_fields() == ["x_dot", "theta"] and d.x_dot == 2.5 and d.sensor_name == "imu"


def test_waypoint_presence() -> None:
    w = m.Waypoint().set(x=10, y=15)
    w.horizontal_threshold = 2.0
    assert w.has("x") and not w.has("time")


def test_enumerate_fields_flattens_nested() -> None:
    c = m.Circle()
    c.base.base.uid = "c1"
    c.radius = 2.0
    fields = dict(m.enumerate_fields(c))
    assert fields["base.base.uid"] == "c1" and fields["radius"] == 2.0
    assert "base.base.header.timestamp_us" in fields and "base.base.header.system_id" in fields


def test_every_type_has_a_unique_fingerprint_and_a_header_at_its_root() -> None:
    names = m.REGISTRY.names()
    fps = {m.REGISTRY.by_name(n)._get_packed_fingerprint() for n in names}
    assert len(fps) == len(names)
    embedded = {"ChannelInfo", "ConfigField", "ChannelStats", "KeyValue", "ServiceState", "CloudPoint", "Header"}
    for n in set(names) - embedded:
        root = m.REGISTRY.ancestry(m.REGISTRY.by_name(n))[-1]
        assert root.__slots__[0] == "header", n


def test_registry_refuses_two_types_with_one_fingerprint() -> None:
    reg = m.TypeRegistry()
    reg.register(m.Circle)

    class Impostor(m.Circle):  # same fields, hence same fingerprint
        pass

    with pytest.raises(ValueError, match="same LCM fingerprint"):
        reg.register(Impostor)


def test_known_child_decodes_to_itself_and_views_as_parent() -> None:
    c = m.Circle()
    c.base.base.uid = "buoy-7"
    c.radius = 1.5
    msg, known = m.REGISTRY.decode(c.encode(), m.ObjectDescription)
    assert known and isinstance(msg, m.Circle)
    assert m.as_type(msg, m.ObjectDescription).uid == "buoy-7"


def test_wrong_type_and_garbage_are_malformed() -> None:
    with pytest.raises(m.MalformedMessage, match="wrong type"):
        m.REGISTRY.decode(m.Health().encode(), m.StateInformation)
    with pytest.raises(m.MalformedMessage, match="truncated"):
        m.REGISTRY.decode(m.StateInformation().encode()[:40], m.StateInformation)
    with pytest.raises(m.MalformedMessage):
        m.REGISTRY.decode(b"\x01\x02", m.StateInformation)


def test_unknown_child_type_decodes_as_its_base(tmp_path: Path) -> None:
    """A Buoy type this process has never imported arrives as an ObjectDescription."""
    lcm_file = tmp_path / "buoy.lcm"
    lcm_file.write_text(textwrap.dedent("""\
        package buoyext;
        struct Buoy { u2sa_hw.lcmtypes.ObjectDescription base; string colour; double height; }
        """))
    subprocess.run([message_codegen.find_lcm_gen(), "-p", "--ppath", str(tmp_path), str(lcm_file)], check=True)
    code = textwrap.dedent("""\
        import sys; sys.path.insert(0, sys.argv[1])
        from buoyext import Buoy
        b = Buoy(); b.base.uid = "red-1"; b.base.object_type = "buoy"; b.base.x = 4.0; b.colour = "red"
        sys.stdout.buffer.write(b.encode())
        """)
    data = subprocess.run([sys.executable, "-c", code, str(tmp_path)], check=True, capture_output=True).stdout
    assert m.REGISTRY.by_fingerprint(data[:8]) is None
    msg, known = m.REGISTRY.decode(data, m.ObjectDescription)
    assert not known and isinstance(msg, m.ObjectDescription)
    assert (msg.uid, msg.object_type, msg.x) == ("red-1", "buoy", 4.0)


def test_generated_code_matches_lcm_files() -> None:
    assert message_codegen.main(["--check"]) == 0


def test_regeneration_check_detects_a_difference(tmp_path: Path) -> None:
    copy = tmp_path / "lcmtypes"
    shutil.copytree(message_codegen.GENERATED_DIR, copy)
    target = copy / "Header.py"
    target.write_text(target.read_text().replace("int64_t", "int32_t", 1))
    generated = message_codegen.generate(tmp_path / "fresh")
    assert message_codegen.differences(generated, copy) == ["Header.py"]


def test_presence_methods_are_generated_into_the_classes_not_patched_at_import() -> None:
    code = textwrap.dedent("""\
        import sys
        from u2sa_hw.lcmtypes import StateInformation, Waypoint
        s = StateInformation().set(x=1.0).set_psi(0.5)
        assert s.present_fields() == ["x", "psi"] and not s.has("y") and s.get("y", 7) == 7
        assert Waypoint().set_time(3).present_fields() == ["time"]
        assert "u2sa_hw.messages" not in sys.modules   # nothing was installed by importing it
        """)
    subprocess.run([sys.executable, "-c", code], check=True)
    source = (message_codegen.GENERATED_DIR / "StateInformation.py").read_text()
    assert "    def set_psi(self, value):" in source and "PRESENCE_FIELDS = (" in source
    assert m.StateInformation.PRESENCE_FIELDS == m.STATE_FIELDS and m.Waypoint.PRESENCE_FIELDS == m.WAYPOINT_FIELDS


def test_a_presence_list_naming_a_field_the_struct_lacks_is_refused() -> None:
    from u2sa_hw.message_presence_gen import add_presence

    source = (message_codegen.GENERATED_DIR / "Waypoint.py").read_text()
    with pytest.raises(ValueError, match="Waypoint: presence fields not in the .lcm struct: speed"):
        add_presence(source, "Waypoint", ("x", "speed"))


def _old_raw_i2c(register: int, data: bytes, *, op: int = 0) -> bytes:
    """A RawI2c as a log made before the rename holds it: the old fingerprint, the same layout."""
    rec = m.RawI2c()
    rec.device, rec.bus, rec.address, rec.register_address, rec.op, rec.ok = "imu", 1, 0x68, register, op, True
    rec.data, rec.length = data, len(data)
    return bytes.fromhex("0e61df589a1e329c") + rec.encode()[8:]


def test_raw_i2c_recorded_with_its_old_field_name_still_decodes() -> None:
    assert "register" not in m.RawI2c.__slots__ and "register_address" in m.RawI2c.__slots__
    old = _old_raw_i2c(0x75, b"\x71")
    assert old[:8] != m.RawI2c._get_packed_fingerprint()
    rec, known = m.REGISTRY.decode(old)
    assert known and type(rec) is m.RawI2c and rec.register_address == 0x75 and rec.data == b"\x71"


def test_an_old_mcap_log_replays_its_i2c_reads(tmp_path: Path) -> None:
    from u2sa_hw.hil.replay_buses import ReplayI2cDevice
    from u2sa_hw.recording.mcap_log import McapFile, RunInfo

    log = tmp_path / "old.mcap"
    f = McapFile(log, compression="none", chunk_size=1024, run=RunInfo(vehicle="old"))
    f.write("RAW.imu", _old_raw_i2c(0x75, b"\x71"), 1_000)
    f.write("RAW.imu", _old_raw_i2c(0x3B, b"\x01\x02"), 2_000)
    f.close()
    device = ReplayI2cDevice(name="imu", socket_path=tmp_path / "i2c.sock", fast=False)
    device.preload(log, start_ns=0, end_ns=10_000)
    assert device.transact(0x68, 0, 0x75, 1, b"") == (0, b"\x71")
    assert device.transact(0x68, 0, 0x3B, 2, b"") == (0, b"\x01\x02")
