"""Seeded fuzz of the CAN motor drivers' frame handling (ODrive CANSimple, VESC STATUS and COMM
buffers), and the impossible values of the issue: one ODrive encoder frame of 3.4e38 turns/s, a
VESC STATUS of 2^31 ERPM. No exception but the drivers' counted decode drops may escape, and the
odometry they publish is finite and within what a wheel can do."""

from __future__ import annotations

import struct
from pathlib import Path

import can
import pytest
from fuzz_targets import CanTarget, run_seeded

from u2sa_hw.protocols import odrive_cansimple as cs
from u2sa_hw.protocols import vesc_can as vc


@pytest.mark.parametrize("kind", ["odrive", "vesc"])
def test_mutated_frames_never_escape_or_publish_impossible_odometry(tmp_path: Path, lcm_url: str, kind: str) -> None:
    target = CanTarget(kind, workdir=tmp_path, lcm_url=lcm_url)
    try:
        run_seeded(target, seed=2024, count=60000)
        svc = target.svc
        assert svc.frames_rx > 60000 and svc.dropped > 100 and svc.out_of_range.total > 100
        assert svc.odometry is not None and svc.odometry.emitted > 10   # the valid frames still made odometry
    finally:
        target.close()


def test_one_odrive_encoder_frame_of_3e38_turns_per_s_is_dropped_not_published(tmp_path: Path, lcm_url: str) -> None:
    target = CanTarget("odrive", workdir=tmp_path, lcm_url=lcm_url)
    try:
        svc = target.svc
        sent = []
        for i, (left, right) in enumerate([(1.0, 1.0), (3.0e38, 1.0), (1.0, float("nan")), (1.0, 1.0)]):
            for node, vel in ((0, left), (1, right)):
                msg = cs.make_frame(node, cs.Cmd.GET_ENCODER_ESTIMATES, cs.encode_encoder_estimates(0.0, vel))
                msg.timestamp = 100.0 + i * 0.01
                svc._dispatch(msg)
            sent += [m.x_dot for m in svc.sent]
            svc.sent.clear()
        # the default wheel_radius_m 0.1: 1 turn/s is 0.628 m/s; the right wheel's sample of the second pair
        # is paired with the left's of the third (the impossible ones in between are dropped, not used)
        assert sent == pytest.approx([2 * 3.141592653589793 * 0.1] * 3)
        assert svc.health_details()["out_of_range_kinds"] == "encoder velocity:2"
    finally:
        target.close()


def test_a_vesc_status_of_2e9_erpm_or_duty_30_is_dropped_not_published(tmp_path: Path, lcm_url: str) -> None:
    target = CanTarget("vesc", workdir=tmp_path, lcm_url=lcm_url)
    try:
        svc = target.svc
        frames = [struct.pack(">ihh", 1400, 0, 100), struct.pack(">ihh", 0x7FFFFFFF, 0, 100),
                  struct.pack(">ihh", -0x80000000, 0, 100), struct.pack(">ihh", 1400, 0, 30000)]
        speeds = []
        for i, data in enumerate(frames):
            for controller in (0, 1):
                msg = can.Message(arbitration_id=vc.ext_id(vc.PacketId.STATUS, controller), data=data,
                                  is_extended_id=True, timestamp=200.0 + i * 0.01)
                svc._dispatch(msg)
            speeds += [m.x_dot for m in svc.sent]
            svc.sent.clear()
        assert len(speeds) == 1 and abs(speeds[0]) < 3.0
        assert svc.health_details()["out_of_range_kinds"] == "duty:2,erpm:4"
        assert svc.health_details()["left.erpm"] == "1400"   # the impossible STATUS never reached health either
    finally:
        target.close()
