"""Failsafe scenarios: ``u2sa sim --scenario FILE`` plays events and reports each actuator output.

The two runs are real ``u2sa sim`` processes (every service a process, LCM multicast and a
simulated CAN bus of their own). They assert the ORDER of what the outputs did around each
event, as the mock devices saw them, and the final state; never a timing. One run plays
every case of the example rover (examples/ground_vehicle/scenarios/all.toml), one the
Ackermann car's takeover through the hardware mux, to keep CI short.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import pytest

from conftest import REPO, U2SA
from u2sa_hw.mocks.actuation import OutputLog
from u2sa_hw.simulation.effects import event_effects
from u2sa_hw.simulation.events import ScenarioError, ScenarioEvent, load_scenario_file
from u2sa_hw.bus.udp_ports import private_udp_port

WHEELS = ("left_wheel", "right_wheel")
# the example rover's rc mux signal_timeout_ms (100) less two frames (20 ms each at 50 Hz): a stall this long beyond
# a frame period can leave the mux without a mode pulse for the timeout (the last one was stamped up to a frame
# before its frame was handed over); a CI run saw NO RC SIGNAL with a 78.8 ms stall
RC_STARVED_MS = 60.0


def play(tmp_path: Path, lcm_url: str, vehicle: str, scenario: str) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    out = tmp_path / "out"
    proc = subprocess.run([*U2SA, "sim", "--vehicle", vehicle, "--scenario", scenario, "--out", str(out),
                           "--lcm-url", lcm_url, "--can-port", str(private_udp_port()), "--timeout", "150"],
                          cwd=REPO, capture_output=True, text=True, timeout=200)
    assert proc.returncode == 0, f"u2sa sim failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-2000:]}"
    summary = json.loads((out / "summary.json").read_text())
    return summary, summary["scenario"]["events"]


def stopped(event: dict[str, Any], names: tuple[str, ...]) -> bool:
    """Every output in *names* went neutral in the event's window and did not move again in it."""
    return all(event["outputs"][n]["neutral_after_ms"] is not None and event["outputs"][n]["moved_after_ms"] is None
               and event["outputs"][n]["at_end"]["neutral"] for n in names)


def moved(event: dict[str, Any], names: tuple[str, ...]) -> bool:
    """Every output in *names* was neutral at the event and moved in its window."""
    return all(event["outputs"][n]["at_event"]["neutral"] and event["outputs"][n]["moved_after_ms"] is not None
               for n in names)


def starved_rc(*events: dict[str, Any]) -> bool:
    """The RC mux heard NO RC SIGNAL in these windows while the simulated receiver (a thread of the sim) stalled
    long enough for the mux's signal timeout: a loss the machine's load made, not the event (the summary says so)."""
    return any(e["rc_receiver_stalled_ms"] is not None and e["rc_receiver_stalled_ms"] >= RC_STARVED_MS
               for e in events) and any("NO RC SIGNAL" in e["rc_modes"] for e in events)


def stopped_or_starved(before: dict[str, Any], event: dict[str, Any]) -> bool:
    """The wheels stopped in *event*'s window, or a starved receiver (in the window before or this one) had the
    mux disarm first and they stayed still (the summary names the stall)."""
    return stopped(event, WHEELS) or (starved_rc(before, event) and still(event, WHEELS))


def moved_or_starved(event: dict[str, Any]) -> bool:
    """The wheels moved in *event*'s window, or a starved receiver in it had the mux disarm and they stayed still."""
    return moved(event, WHEELS) or (starved_rc(event) and still(event, WHEELS))


def still(event: dict[str, Any], names: tuple[str, ...]) -> bool:
    """Every output in *names* was neutral at the event and stayed neutral through its window."""
    return all(event["outputs"][n]["at_event"]["neutral"] and event["outputs"][n]["moved_after_ms"] is None
               for n in names)


@pytest.mark.timeout(240)
def test_every_failsafe_case_of_the_example_rover_in_order(tmp_path: Path, lcm_url: str) -> None:
    summary, events = play(tmp_path, lcm_url, "examples/ground_vehicle/vehicle.toml",
                           "examples/ground_vehicle/scenarios/all.toml")
    by = {e["event"]: e for e in events}
    assert [e["action"] for e in events] == ["rc_loss", "rc_return", "reengage", "mode", "forge", "sticks", "centre",
                                             "mode", "failsafe", "failsafe", "reengage", "gps_fix", "gps_fix",
                                             "reengage", "signal", "signal", "signal"]
    rc_loss, rc_return, rearm1, manual, forge, sticks, centre, auto, fs_on, fs_off, rearm2, gps_off, gps_on, \
        rearm3, stop, cont, kill = events
    # RC loss: the wheels stop; the link back is not enough, only the pilot's re-arm drives again
    assert stopped(rc_loss, WHEELS) and "NO RC SIGNAL" in rc_loss["rc_modes"]
    # Where the simulated RC receiver's thread was not run for about the mux's signal timeout (an overloaded
    # machine: make test on a busy 2-core VM), the mux rightly heard no pulses and disarmed: an event that was to
    # stop the wheels finds them already still, a move waits for the next re-arm (*_or_starved, and only then)
    assert still(rc_return, WHEELS) and moved_or_starved(rearm1)
    # manual: the autonomous commands stop at every wheel; a forged one is dropped; the sticks drive
    assert stopped_or_starved(rearm1, manual) and manual["rc_modes"][-1] == "MANUAL"
    assert still(forge, WHEELS)
    assert moved_or_starved(sticks) and stopped_or_starved(sticks, centre)
    assert moved_or_starved(auto)
    # an operator failsafe stops everything; its clear does not restart anything; a re-arm does
    assert stopped_or_starved(auto, fs_on) and still(fs_off, WHEELS) and moved_or_starved(rearm2)
    # the GPS fix lost: the pre-arm check stops the wheels until the fix is back and the pilot re-arms
    assert stopped_or_starved(rearm2, gps_off)
    assert any("gps" in mode for mode in gps_off["rc_modes"]) or starved_rc(rearm2, gps_off)
    assert still(gps_on, WHEELS) and moved_or_starved(rearm3)
    # control frozen: the wheels' dead-man stops them; resumed, it drives again
    assert stopped_or_starved(rearm3, stop)
    # (only for the two signs of a starved machine: any other block after a freeze is a failure)
    failed_safe = [m for m in cont["rc_modes"] if "no health for over" in m or m == "NO RC SIGNAL"]
    if failed_safe:
        # A machine too loaded to keep the RC pulses and the services' health flowing (make test-stress: "no
        # health for over 3 s" from the frozen control, then NO RC SIGNAL): the mux failed safe, and stays
        # disarmed until the pilot re-arms. Nothing may move meanwhile, the killed driver's wheels included.
        assert still(cont, WHEELS) and still(kill, WHEELS), failed_safe
    else:
        assert moved(cont, WHEELS)
        # the wheels driver killed: the motors stop (the controllers' own watchdog) before anything else
        assert all(kill["outputs"][n]["neutral_after_ms"] is not None for n in WHEELS)
    assert by[kill["event"]]["outputs"]["pan"]["at_event"]["neutral"]
    # final state: every output neutral after the run stopped the stack
    assert all(o["neutral"] for o in summary["outputs"].values()) and set(summary["outputs"]) >= {*WHEELS, "pan"}


@pytest.mark.timeout(200)
def test_the_ackermann_car_is_taken_over_through_the_hardware_mux(tmp_path: Path, lcm_url: str) -> None:
    summary, events = play(tmp_path, lcm_url, "examples/ackermann_rover/vehicle.toml",
                           "examples/ackermann_rover/scenarios/manual_takeover.toml")
    manual, sticks, centre, auto, rc_loss, rc_return, rearm = events
    throttle = ("throttle",)
    # the PWM outputs move the simulated car: it drove before the takeover
    assert summary["distance_m"] > 3
    # manual: the mux passes the pilot's centred sticks at once; then the sticks themselves. A throttle already
    # neutral at the switch (on a loaded machine the car may not be moving 3 s after engaging: its dead-man or a
    # lost autonomy) must stay so: what is asserted is that nothing moves it after the pilot takes over
    assert stopped(manual, throttle) or still(manual, throttle), (manual["outputs"]["throttle"], manual["rc_modes"],
                                                                  summary["autonomy_interruptions"])
    assert moved(sticks, ("throttle", "steering"))
    assert sticks["outputs"]["steering"]["at_end"]["value"] < 0 < sticks["outputs"]["throttle"]["at_end"]["value"]
    assert stopped(centre, ("throttle", "steering")) and moved(auto, throttle)
    # RC lost: the mux selects the pilot, whose receiver puts out nothing: the ESC has no pulse
    assert stopped(rc_loss, throttle) and rc_loss["outputs"]["throttle"]["at_end"]["value"] == 0.0
    assert still(rc_return, throttle) and moved(rearm, throttle)
    assert all(o["neutral"] for o in summary["outputs"].values())


# ---- the scenario file and the effects, without a simulation ---------------------------------
@pytest.mark.parametrize("text, error", [
    ("", r"scen.toml: no \[\[event\]\] tables"),
    ("[[event]]\nat_s = 1\naction = \"explode\"\n", r"scen.toml event\[0\]: action 'explode' is not one of rc_loss"),
    ("[[event]]\nat_s = -1\naction = \"rc_loss\"\n", r"event\[0\]: at_s must be a number of seconds >= 0"),
    ("[[event]]\nat_s = 1\naction = \"mode\"\nvalue = \"auto\"\n", r"mode value must be \"manual\" or \"autonomous\""),
    ("[[event]]\nat_s = 1\naction = \"signal\"\nservice = \"gps\"\nsignal = \"HUP\"\n",
     r"signal must be one of KILL, STOP, CONT, TERM"),
    ("[[event]]\nat_s = 1\naction = \"sticks\"\nthrottle = 2\n", r"sticks throttle must be a position -1..1"),
    ("[[event]]\nat_s = 1\naction = \"forge\"\nactuator = \"x\"\n", r"forge needs percent"),
    ("[[event]]\nat_s = 1\naction = \"rc_loss\"\nfor_s = 2\n", r"unknown key\(s\) for_s for rc_loss"),
    ("end_s = 0.5\n[[event]]\nat_s = 1\naction = \"rc_loss\"\n", r"end_s must be a number >= the last event"),
])
def test_a_bad_scenario_names_the_file_the_event_and_the_key(tmp_path: Path, text: str, error: str) -> None:
    path = tmp_path / "scen.toml"
    path.write_text(text)
    with pytest.raises(ScenarioError, match=error):
        load_scenario_file(path)


def test_every_shipped_scenario_loads() -> None:
    files = sorted(REPO.glob("examples/*/scenarios/*.toml"))
    assert {f.stem for f in files} >= {"rc_loss", "manual_switch", "sticks", "gps_fix_loss", "service_kill",
                                       "forged_command", "failsafe", "all", "manual_takeover"}
    for path in files:
        assert load_scenario_file(path).events


def test_effects_say_when_each_output_went_neutral_and_moved_again() -> None:
    log = OutputLog()
    ms = 1_000_000
    for name, t, value in (("a", 0, 0.0), ("b", 0, 0.0), ("a", 10, 50.0), ("b", 12, 40.0), ("a", 30, 55.0),
                           ("a", 105, 0.0), ("b", 140, 0.0),
                           ("a", 400, 30.0)):
        log.record(name, value, neutral=value == 0.0, t_ns=t * ms)
    events = [(ScenarioEvent(1.0, "rc_loss"), 100 * ms), (ScenarioEvent(2.0, "reengage"), 300 * ms)]
    loss, rearm = event_effects(log, events, end_ns=500 * ms, t0_ns=0, rc_modes=[(120 * ms, "NO RC SIGNAL")],
                                rc_stalls=[(150 * ms, 60 * ms), (170 * ms, 95 * ms), (300 * ms, 70 * ms)])
    assert loss["rc_receiver_stalled_ms"] == 95.0 and rearm["rc_receiver_stalled_ms"] is None
    assert starved_rc(loss) and not starved_rc(rearm)
    quiet = dict(loss, rc_receiver_stalled_ms=55.0)   # a stall too short for the mux's timeout: no excuse
    assert not starved_rc(quiet)
    assert loss["outputs"]["a"]["neutral_after_ms"] == 5.0 and loss["outputs"]["a"]["moved_after_ms"] is None
    assert loss["all_neutral_after_ms"] == 40.0 and loss["rc_modes"] == ["NO RC SIGNAL"]
    assert rearm["all_neutral_after_ms"] == 0.0 and rearm["outputs"]["a"]["moved_after_ms"] == 100.0
    assert rearm["outputs"]["b"]["moved_after_ms"] is None and rearm["outputs"]["a"]["at_end"]["value"] == 30.0
