"""No latch from a stall (issue 27): a controller's watchdog trip caused by its own driver's stall is
cleared on the pilot's next re-arm through manual; a hardware fault, an unexplained watchdog trip or a
trip with no re-arm stays latched. The rule as pure logic (times passed in), then the ODrive driver
object against two mock ODrive axes on a virtual bus, stalled for real (its lock held until the axes'
watchdogs trip), then the pre-arm line that names the fix. No timing asserts: order and counts."""

from __future__ import annotations

import logging
import random
import threading
import time
from typing import Any, Iterator

import pytest
from conftest import wait_until

from u2sa_hw.profile.vehicle import VehicleProfile
from u2sa_hw.drivers.can_motor.odrive.driver import OdriveCanMotor
from u2sa_hw.drivers.can_motor.stall_trip import Stall, StallWatch, Trip, may_clear, trip_gap_s
from u2sa_hw.mocks.odrive_config import ENABLE_WATCHDOG_ENDPOINT, MOCK_FW, WATCHDOG_TIMEOUT_ENDPOINT
from u2sa_hw.mocks.odrive_node import OdriveCanNode
from u2sa_hw.mocks.vehicle_sim import SimVehicle
from u2sa_hw import lcmtypes as t
from u2sa_hw.protocols.odrive_cansimple import AxisState, Cmd, OdriveError
from u2sa_hw.safety.gate import RC_MODE_AUTONOMOUS, RC_MODE_MANUAL, CommandGate
from u2sa_hw.safety.prearm import PrearmChecks
from u2sa_hw.profile.loader import load_profile

from test_prearm import OK, health, write_profile

WD = int(OdriveError.WATCHDOG_TIMER_EXPIRED)
OVER_CURRENT = int(OdriveError.CURRENT_LIMIT_VIOLATION)
NODES = (3, 4)
WATCHDOG_06 = {"watchdog_timeout_endpoint": WATCHDOG_TIMEOUT_ENDPOINT,
               "enable_watchdog_endpoint": ENABLE_WATCHDOG_ENDPOINT, "endpoints_fw": MOCK_FW}


def bus_profile(address: str) -> VehicleProfile:
    """A profile (no file) whose device ``motors`` is the CAN bus at *address*."""
    return VehicleProfile(path=None, devices={"motors": {"address": address}})



def rc_mode(mode: int, *, armed: bool) -> t.RcMode:
    msg = t.RcMode()
    msg.mode, msg.armed = mode, armed
    return msg


# ---------------------------------------------------------------- the rule, pure ---------------
def watch_with_stall(start: float, end: float) -> StallWatch:
    watch = StallWatch(wall=lambda: 1_700_000_000.0)
    for now in (start - 0.02, start - 0.01, start, end, end + 0.01):
        watch.turn(now)
    return watch


def test_the_loop_gaps_are_the_stalls_and_say_how_long_and_when() -> None:
    watch = watch_with_stall(10.0, 10.52)
    assert watch.count == 1 and [round(s.duration, 2) for s in watch.stalls] == [0.52]
    text = watch.stalls[0].describe()
    assert text.startswith("sent nothing for 0.52 s from ") and text.endswith(" UTC")
    assert watch.details()["longest_stall_s"] == "0.52" and watch.details()["stalls"] == 1
    assert watch.turn(9.0) is None and watch.count == 1, "a clock that went back is no stall"


def test_a_stall_trip_is_cleared_on_a_re_arm_after_it_and_only_then() -> None:
    watch = watch_with_stall(10.0, 10.5)
    trip = Trip(WD, seen=10.5, watchdog_only=True, rearms=3)   # the error heartbeat read on waking
    assert trip.attribute(watch, min_s=trip_gap_s(watchdog_timeout_s=0.3, command_period_s=0.05)) is not None
    assert trip.stall_trip
    assert not may_clear(trip, bits_now=WD, rearms_now=3, link_up=True), "no re-arm since the trip: latched"
    assert not may_clear(trip, bits_now=WD, rearms_now=4, link_up=False), "the link is not back: latched"
    assert not may_clear(trip, bits_now=WD | OVER_CURRENT, rearms_now=4, link_up=True), "another error since"
    assert may_clear(trip, bits_now=WD, rearms_now=4, link_up=True)


@pytest.mark.parametrize("why, bits, watchdog_only, seen, stall", [
    ("a hardware fault", OVER_CURRENT, False, 10.5, (10.0, 10.5)),
    ("a hardware fault beside the watchdog bit", WD | OVER_CURRENT, False, 10.5, (10.0, 10.5)),
    ("a watchdog trip with no stall of the driver (frames lost on the bus?)", WD, True, 10.5, None),
    ("a stall too short to starve a 0.3 s watchdog", WD, True, 10.2, (10.0, 10.2)),
    ("a trip first heard long after the stall ended", WD, True, 14.0, (10.0, 10.5)),
    ("a trip heard before the stall began", WD, True, 9.0, (10.0, 10.5)),
])
def test_anything_but_a_proven_stall_trip_stays_latched_through_a_re_arm(why: str, bits: int, watchdog_only: bool,
                                                                          seen: float, stall: Any) -> None:
    watch = watch_with_stall(*stall) if stall else StallWatch()
    trip = Trip(bits, seen=seen, watchdog_only=watchdog_only, rearms=0)
    trip.attribute(watch, min_s=trip_gap_s(watchdog_timeout_s=0.3, command_period_s=0.05))
    assert not trip.stall_trip, why
    assert not may_clear(trip, bits_now=bits, rearms_now=5, link_up=True), why
    assert not may_clear(None, bits_now=bits, rearms_now=5, link_up=True)


def test_the_gate_counts_the_pilots_re_arms_through_manual() -> None:
    gate = CommandGate(rc_mode_timeout_s=0.25)
    gate.on_rc_mode(rc_mode(RC_MODE_MANUAL, armed=True), 0.0)
    assert gate.rearms == 0, "the first RC_MODE heard: what came before it is unknown"
    gate.on_rc_mode(rc_mode(RC_MODE_MANUAL, armed=True), 0.1)
    assert gate.rearms == 0, "still in manual: no movement"
    gate.on_rc_mode(rc_mode(RC_MODE_AUTONOMOUS, armed=False), 0.2)   # refused: the mux disarmed
    gate.on_rc_mode(rc_mode(RC_MODE_MANUAL, armed=True), 0.3)
    assert gate.rearms == 1
    gate.on_rc_mode(rc_mode(RC_MODE_AUTONOMOUS, armed=True), 0.4)
    gate.on_rc_mode(rc_mode(RC_MODE_MANUAL, armed=True), 0.5)        # the pilot takes over: through manual
    assert gate.rearms == 2
    gate.on_rc_mode(rc_mode(2, armed=False), 0.6)                    # no signal
    gate.on_rc_mode(rc_mode(RC_MODE_MANUAL, armed=False), 0.7)       # manual, not yet confirmed
    assert gate.rearms == 2
    gate.on_rc_mode(rc_mode(RC_MODE_MANUAL, armed=True), 0.8)
    assert gate.rearms == 3


# ---------------------------------------------------------------- the driver, stalled for real --
class Rig:
    """Two mock ODrive axes (0.3 s watchdog written by the driver) on a virtual bus, the driver on a thread."""

    def __init__(self) -> None:
        self.channel = f"stall-trip-{random.randint(0, 1 << 30)}"
        self.vehicle = SimVehicle(origin_lat=0.0, origin_lon=0.0)
        self.nodes = {side: OdriveCanNode(self.vehicle, side=side, node_id=node_id, interface="virtual",
                                          channel=self.channel, vel_limit=10.0)
                      for side, node_id in zip(("left", "right"), NODES)}
        self.svc = OdriveCanMotor("motors", profile=bus_profile(f"can://virtual/{self.channel}"), settings={
            "node_ids": list(NODES), "status_poll_s": 0.0,
            "odometry": False, "rc_gating": False, "command_timeout_s": 0.5, "silent_after_s": 0.5, **WATCHDOG_06})
        self.runner = threading.Thread(target=self.svc.run, daemon=True)

    def details(self) -> dict[str, Any]:
        return self.svc.health_details()

    def wait(self, predicate: Any, message: str, timeout: float = 20.0) -> dict[str, Any]:
        return wait_until(lambda: (d := self.details()) and predicate(d) and d, timeout=timeout, message=message)

    def pilot(self, *modes: tuple[int, bool]) -> None:
        """RC_MODE messages as the RC mux publishes them, handed to the driver's gate in order."""
        for mode, armed in modes:
            self.svc.gate.on_rc_mode(rc_mode(mode, armed=armed), time.monotonic())

    def heartbeats_sent(self, side: str) -> int:
        return sum(1 for r in self.nodes[side].history
                   if r.direction == "tx" and r.message.arbitration_id & 0x1F == Cmd.HEARTBEAT)

    def stall(self, *, heartbeats: int) -> None:
        """The driver's loop holds still (its lock taken) until both axes' watchdogs have tripped and each node
        has sent *heartbeats* more heartbeats (at 10 Hz: a stall longer than silent_after_s)."""
        marks = {side: self.heartbeats_sent(side) for side in self.nodes}
        with self.svc.lock:
            wait_until(lambda: all(n.watchdog_trips for n in self.nodes.values())
                       and all(self.heartbeats_sent(s) - marks[s] >= heartbeats for s in self.nodes), timeout=20,
                       message="both axis watchdogs tripped while the driver stalled")

    def frames_after(self, count: int) -> None:
        """Wait until each node has received *count* more frames from the driver (its loop turned on)."""
        marks = {side: len(node.history) for side, node in self.nodes.items()}
        wait_until(lambda: all(len(n.history) - marks[s] >= count for s, n in self.nodes.items()), timeout=20,
                   message=f"{count} more frames to each node")

    def clears_sent(self, side: str) -> int:
        return sum(1 for r in self.nodes[side].history
                   if r.direction == "rx" and r.message.arbitration_id & 0x1F == Cmd.CLEAR_ERRORS)


@pytest.fixture
def rig(lcm_url: str) -> Iterator[Rig]:
    r = Rig()
    r.vehicle.start()
    for node in r.nodes.values():
        node.start()
    r.svc.start()
    r.runner.start()
    try:
        yield r
    finally:
        r.svc.stop()
        r.runner.join(timeout=10)
        r.svc.kill()
        r.svc.transport.stop()
        for node in r.nodes.values():
            node.stop()
        r.vehicle.stop()


def test_a_stall_trip_is_logged_and_cleared_on_the_pilots_re_arm_and_a_hardware_fault_is_not(
        rig: Rig, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    rig.wait(lambda d: d["left.phase"] == d["right.phase"] == "armed" and d["hw_watchdog"].startswith("on"),
             "both axes armed with their watchdogs on")
    rig.pilot((RC_MODE_MANUAL, True))   # the pilot is in manual, armed, before the stall
    rig.stall(heartbeats=7)

    # each trip is attributed at the driver's tick after its error heartbeat: wait for both in the reason
    details = rig.wait(lambda d: d["left.phase"] == d["right.phase"] == "error"
                       and all(f"{side} (node {node}) error WATCHDOG_TIMER_EXPIRED (this driver stalled"
                               in d["degraded_reason"] for side, node in zip(("left", "right"), NODES)),
                       "both axes latched with a trip this driver's stall explains")
    assert details["to_clear"].startswith("switch through manual to re-arm")
    assert int(details["stalls"]) >= 1 and details["last_stall"].startswith("sent nothing for ")
    assert any("from this driver's own stall (sent nothing for" in r.getMessage() for r in caplog.records)
    # the stall outlasted silent_after_s (0.5 s), but the heartbeats that waited meanwhile say the nodes are there
    assert details["left.silent_events"] == details["right.silent_events"] == 0

    # no re-arm: still latched however long the driver runs (a still switch in manual is no re-arm)
    rig.pilot((RC_MODE_MANUAL, True))
    rig.frames_after(20)
    details = rig.details()
    assert details["left.phase"] == details["right.phase"] == "error"
    cleared_before = {side: rig.clears_sent(side) for side in rig.nodes}

    # the pilot tries autonomy (refused, disarmed), then re-arms through manual: cleared, re-armed, logged
    rig.pilot((RC_MODE_AUTONOMOUS, False), (RC_MODE_MANUAL, True))
    details = rig.wait(lambda d: d["left.phase"] == d["right.phase"] == "armed", "both axes re-armed")
    assert details["left.stall_clears"] == details["right.stall_clears"] == 1
    assert all(rig.clears_sent(side) > cleared_before[side] for side in rig.nodes)
    cleared = [r.getMessage() for r in caplog.records if "clearing WATCHDOG_TIMER_EXPIRED on the pilot's re-arm"
               in r.getMessage()]
    assert len(cleared) == 2 and all("own stall (sent nothing for" in line for line in cleared)
    rig.wait(lambda d: d["to_clear"] == "" and rig.svc.status == "ok", "nothing latched, not degraded")
    assert all(node.axis_state == AxisState.CLOSED_LOOP_CONTROL for node in rig.nodes.values())

    # a hardware fault: the pilot's re-arm does not clear it; the deliberate clear does
    rig.nodes["right"].inject_error(OVER_CURRENT)
    details = rig.wait(lambda d: d["right.phase"] == "error" and "CURRENT_LIMIT" in d["degraded_reason"],
                       "the over-current latched")
    assert details["to_clear"] == "u2sa param set motors clear_errors true"
    assert "right (node 4) error CURRENT_LIMIT_VIOLATION (latched)" in details["degraded_reason"]
    rig.pilot((RC_MODE_AUTONOMOUS, False), (RC_MODE_MANUAL, True))
    rig.frames_after(20)
    assert rig.details()["right.phase"] == "error" and rig.nodes["right"].axis_error == OVER_CURRENT
    rig.svc.config.set("clear_errors", True)
    rig.svc.on_config_change("clear_errors", True)
    rig.wait(lambda d: d["right.phase"] == "armed", "re-armed after the deliberate clear")


def test_a_watchdog_trip_the_driver_did_not_cause_stays_latched_through_a_re_arm(rig: Rig) -> None:
    rig.wait(lambda d: d["left.phase"] == d["right.phase"] == "armed", "both axes armed")
    rig.pilot((RC_MODE_MANUAL, True))
    rig.nodes["left"].inject_error(WD)   # the node says its watchdog expired; this driver never stalled
    details = rig.wait(lambda d: d["left.phase"] == "error" and "(latched)" in d["degraded_reason"], "the trip latched")
    trip = rig.svc.axes["left"].trip
    if trip is not None and trip.stall is not None:
        pytest.skip(f"this machine stalled the driver itself just then ({trip.stall.describe()})")
    assert details["to_clear"] == "u2sa param set motors clear_errors true"
    rig.pilot((RC_MODE_AUTONOMOUS, False), (RC_MODE_MANUAL, True))
    rig.frames_after(20)
    details = rig.details()
    assert details["left.phase"] == "error" and details["left.stall_clears"] == 0


# ---------------------------------------------------------------- the pre-arm line -------------
@pytest.mark.parametrize("fix", ["u2sa param set wheels clear_errors true",
                                 "switch through manual to re-arm (clears a watchdog trip of the driver's own stall)"])
def test_a_refusal_on_a_latched_error_names_the_fix(tmp_path, fix: str) -> None:
    services = {"wheels": {"kind": "odrive_can"}, "rc": {"kind": "rc_mux"}}
    checks = PrearmChecks.from_profile(load_profile(write_profile(tmp_path, services=services)))
    checks.on_health(health("wheels", "degraded", degraded_reason="left (node 0) error WATCHDOG_TIMER_EXPIRED "
                                                                   "(latched)", to_clear=fix), 0.0)
    failures = checks.evaluate(0.1, **OK)
    assert [f.reason for f in failures] == [
        f"required service wheels: degraded (left (node 0) error WATCHDOG_TIMER_EXPIRED (latched); to clear: {fix})"]
    checks.on_health(health("wheels", "degraded", degraded_reason="CAN bus reconnecting", to_clear=""), 0.2)
    assert checks.evaluate(0.3, **OK)[0].reason == "required service wheels: degraded (CAN bus reconnecting)"


def test_stall_durations_are_reported_as_measured() -> None:
    stall = Stall(start=1.0, end=1.75, wall_start=0.0)
    assert stall.describe() == "sent nothing for 0.75 s from 00:00:00.000 UTC"
