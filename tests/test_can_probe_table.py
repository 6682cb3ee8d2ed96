"""The CAN probe's protocol table: each protocol a CAN motor driver declares names a module that recognises
its own family's frames and only those (issue 25: a third family is its protocol module and one line).

Walks :data:`u2sa_hw.registry.CAN_PROTOCOLS`; every frame comes from a protocol module itself
(``probe_frame``), so a new family's module is checked the day its table line is added.
"""

from __future__ import annotations

from itertools import permutations
from types import SimpleNamespace

import pytest

from u2sa_hw.ports.can.probe import heard_nodes, seen_as
from u2sa_hw.drivers.can_motor.declarations import CanMotorDeclarations
from u2sa_hw.registry import CAN_PROTOCOLS, SERVICE_KINDS, can_protocol, resolve_kind

PROTOCOLS = sorted(CAN_PROTOCOLS)
NODE = 5
NODES = (0, 1, 5, 31)   # a node id that puts cmd/packet bits where another family looks (1: 0x701 & 0x1F == 1)


@pytest.mark.parametrize("protocol", PROTOCOLS)
def test_each_protocol_has_a_recogniser_a_frame_and_a_name(protocol: str) -> None:
    module = can_protocol(protocol)
    assert callable(getattr(module, "probe_node", None)), f"{protocol}: no probe_node(frame)"
    assert callable(getattr(module, "probe_frame", None)), f"{protocol}: no probe_frame(node_id)"
    assert isinstance(getattr(module, "PROBE_SEEN", None), str) and module.PROBE_SEEN.strip()
    assert seen_as(protocol) == module.PROBE_SEEN


@pytest.mark.parametrize("protocol", PROTOCOLS)
def test_each_protocol_recognises_its_own_frame(protocol: str) -> None:
    module = can_protocol(protocol)
    for node in NODES:
        assert module.probe_node(module.probe_frame(node)) == node
    assert heard_nodes([module.probe_frame(NODE), module.probe_frame(2), module.probe_frame(NODE)], protocol) == [2, NODE]


@pytest.mark.parametrize(("protocol", "other"), list(permutations(PROTOCOLS, 2)))
def test_each_protocol_ignores_the_other_familys_frame(protocol: str, other: str) -> None:
    frames = [can_protocol(other).probe_frame(node) for node in NODES]
    for frame in frames:
        assert can_protocol(protocol).probe_node(frame) is None, f"{protocol} took {other}'s frame {frame} for a node"
    assert heard_nodes(frames, protocol) == []


@pytest.mark.parametrize("protocol", PROTOCOLS)
def test_a_request_on_a_recognised_id_is_no_node(protocol: str) -> None:
    """A remote (RTR) frame is someone asking, not a node speaking."""
    frame = can_protocol(protocol).probe_frame(NODE)
    asked = SimpleNamespace(arbitration_id=frame.arbitration_id, is_extended_id=frame.is_extended_id,
                            is_remote_frame=True, data=b"")
    assert can_protocol(protocol).probe_node(asked) is None


def test_every_can_motor_drivers_protocol_is_in_the_table() -> None:
    """The protocol each registered CAN motor driver declares for the probe names a table entry (else the probe
    would hear none of its nodes)."""
    drivers = {kind: resolve_kind(kind) for kind in SERVICE_KINDS if ".can_motor." in SERVICE_KINDS[kind]}
    assert drivers, "no CAN motor driver registered"
    for kind, cls in drivers.items():
        assert issubclass(cls, CanMotorDeclarations), kind
        assert cls.PROTOCOL in CAN_PROTOCOLS, f"{kind}: PROTOCOL {cls.PROTOCOL!r} is not in CAN_PROTOCOLS"


def test_odrive_takes_no_canopen_heartbeat_for_a_node() -> None:
    """A CANopen node 1's heartbeat (0x701, one byte) has ODrive's heartbeat cmd bits: only its length differs."""
    import can

    canopen = can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False)
    assert can_protocol("odrive").probe_node(canopen) is None


def test_an_unknown_protocol_hears_nothing_and_says_frames() -> None:
    frames = [can_protocol(p).probe_frame(NODE) for p in PROTOCOLS]
    assert heard_nodes(frames, "") == []
    assert seen_as("canopen") == "frames"
