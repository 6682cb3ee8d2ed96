"""``--compare`` where the recording machine held a service up, and at the ends of command streams
(hil/held_up.py, hil/compare.py).

- The RC mux counts its loop's stalls and the timed messages it skipped for lateness in its health: a
  replay runs on the recorded stamps and reproduces neither, so what differs between the health message
  before a counter grew and the one after (widened by HELD_MARGIN_S) is a note naming the window; the same
  difference anywhere else still counts.
- A command stream holds one sequence per actuator (the mux's MANUAL_CMD: a message per stick output per
  frame), so a frame cut at an end is one message of each actuator, all within the edge."""

from __future__ import annotations

from pathlib import Path

from test_health_watch import mux_health

from u2sa_hw.hil.compare_stream import compare_stream
from u2sa_hw.hil.compare_values import Sample
from u2sa_hw.hil.held_up import HELD_MARGIN_S, HeldWindow, held_up_counters, held_windows, late_edge_windows
from u2sa_hw import lcmtypes as t
from u2sa_hw.recording.mcap_log import McapLogWriter

S = 1_000_000_000


def mode(k: int, *, armed: int = 1, pulse: int | None = None) -> Sample:
    steering = 1000 + 10 * k   # the sticks move: each message its own
    return Sample(S + k * 50_000_000, "RcMode", {"mode": 0, "armed": armed,
                                                 "pulse_us": (steering if pulse is None else pulse, 1500, 1000)})


def command(k: int, actuator: str) -> Sample:
    return Sample(S + k * 40_000_000, "PercentageCommand", {"base.actuator_name": actuator, "percentage": 0.0})


def frames(n: int) -> list[Sample]:
    return [command(k, a) for k in range(n) for a in ("left_wheel", "right_wheel")]


def test_a_difference_inside_a_held_up_window_is_a_note_and_outside_it_counts() -> None:
    rec = [mode(k) for k in range(40)]
    rep = [mode(k, pulse=1001 + 10 * k) if k in (10, 30) else mode(k) for k in range(40)]
    window = HeldWindow("rc", rec[8].t_ns, rec[12].t_ns, "stalls +2")
    r = compare_stream("RC_MODE [rc]", rec, rep, tolerance=1e-6, edge=1, rate=None, time_tolerance_s=0.5,
                       held=[window])
    assert (r.differing, r.matched) == (1, 38) and not r.ok   # #30 is outside: still a difference
    [note] = [n for n in r.notes if "held rc up" in n]
    assert note.startswith("1 difference(s)") and "stalls +2" in note
    # without the window both count
    r = compare_stream("RC_MODE [rc]", rec, rep, tolerance=1e-6, edge=1, rate=None, time_tolerance_s=0.5)
    assert r.differing == 2


def test_an_unpaired_message_inside_a_held_up_window_is_a_note() -> None:
    rec = [mode(k) for k in range(40)]
    rep = rec[:20] + [mode(20, armed=0)] + rec[20:]   # one more message, published while held up
    window = HeldWindow("rc", rec[18].t_ns, rec[22].t_ns, "timed_skipped +1")
    r = compare_stream("RC_MODE [rc]", rec, rep, tolerance=1e-6, edge=1, rate=None, time_tolerance_s=0.5,
                       held=[window])
    assert r.ok and r.inserted == 0, (r.problems, r.notes)


def test_a_message_missing_from_a_run_of_equal_ones_is_judged_anywhere_in_the_run() -> None:
    """Sticks held still: every frame the same. Live, the mux held up in a window early in the log sent one frame
    more; the alignment leaves out the run's *last* message (it cannot tell which is missing), far from the
    window. The run reaches into the window, so it is a note; a run that does not, counts."""
    rec = frames(60)
    rep = frames(59)
    window = HeldWindow("rc", rec[10].t_ns, rec[14].t_ns, "stalls +1")
    r = compare_stream("MANUAL_CMD [rc]", rec, rep, tolerance=1e-6, edge=0, rate=None, time_tolerance_s=0.5,
                       held=[window])
    assert r.ok and r.deleted == 0, (r.problems, r.notes)
    assert any("held rc up" in n for n in r.notes)
    moving = [Sample(c.t_ns, c.type_name, {**c.fields, "percentage": float(k // 2)}) for k, c in enumerate(rec)]
    r = compare_stream("MANUAL_CMD [rc]", moving, moving[:-2], tolerance=1e-6, edge=0, rate=None,
                       time_tolerance_s=0.5, held=[window])
    assert r.deleted == 2 and not r.ok   # the sticks moved: the missing frame is the last one, outside the window


def test_verdict_changes_excuse_at_most_one_unpaired_message_each() -> None:
    """Two verdict changes in a run of equal RC_MODEs (a disarm and the re-arm; `armed` does not steer the
    alignment) on the recorded side only: both are notes. Two more timed messages than that still count."""
    steady = [mode(k, pulse=1500) for k in range(40)]
    rec = steady[:20] + [mode(20, armed=0, pulse=1500), mode(21, pulse=1500)] + steady[20:]
    r = compare_stream("RC_MODE [rc]", rec, steady, tolerance=1e-6, edge=0, rate=None, time_tolerance_s=0.5)
    assert r.ok and r.deleted == 0, (r.problems, r.notes)
    assert any("published for a change of such a verdict" in n for n in r.notes)
    extra = steady[:10] + [mode(10, pulse=1500), mode(11, pulse=1500)] + rec[10:]
    r = compare_stream("RC_MODE [rc]", extra, steady, tolerance=1e-6, edge=0, rate=None, time_tolerance_s=0.5)
    assert r.deleted == 2 and not r.ok, (r.problems, r.notes)


def test_a_frame_cut_at_the_end_of_a_command_stream_is_within_the_edge() -> None:
    rec, rep = frames(20), frames(21)   # the replay published one frame more: a message for each actuator
    r = compare_stream("MANUAL_CMD [rc]", rec, rep, tolerance=1e-6, edge=1, rate=None, time_tolerance_s=0.5)
    assert r.ok and (r.matched, r.inserted) == (40, 0), (r.problems, r.notes)
    rep = frames(22)   # two frames more: beyond the edge
    r = compare_stream("MANUAL_CMD [rc]", rec, rep, tolerance=1e-6, edge=1, rate=None, time_tolerance_s=0.5)
    assert r.inserted == 2 and not r.ok


def test_windows_are_where_the_muxs_health_counters_grew(tmp_path: Path) -> None:
    log = McapLogWriter(tmp_path, path=tmp_path / "run.mcap")
    counts = [(0, 0), (0, 0), (2, 1), (2, 1), (3, 1)]   # (stalls, timed_skipped) at 1 s intervals
    for k, (stalls, skipped) in enumerate(counts):
        log.write("U2SA_HEALTH", mux_health("rc", stalls=stalls, timed_skipped=skipped).encode(), (k + 1) * S)
        # a motor driver's stall counter is its own (not the machine's); its taken_late is the machine's
        log.write("U2SA_HEALTH", mux_health("wheels", stalls=k, taken_late=int(k >= 3)).encode(), (k + 1) * S)
        log.write("U2SA_HEALTH", mux_health("drive", rc_mode_stale=0, taken_late=2 * int(k >= 1)).encode(), (k + 1) * S)
    log.close()
    counters = held_up_counters({"rc": "rc_mux", "wheels": "odrive_can", "drive": "pwm_servo", "gps": "gps_nmea"})
    assert counters == {"rc": ("stalls", "timed_skipped", "checks_lost"), "wheels": ("taken_late",),
                        "drive": ("rc_mode_stale", "taken_late")}
    windows = held_windows(tmp_path / "run.mcap", counters, start_ns=S)
    margin = int(HELD_MARGIN_S * S)
    assert [(w.from_ns, w.to_ns, w.why) for w in windows["rc"]] == [
        (2 * S - margin, 3 * S + margin, "stalls +2, timed_skipped +1"), (4 * S - margin, 5 * S + margin, "stalls +1")]
    # a backlog taken late between two health messages (no stale RC_MODE, the loop on time when health went out)
    assert [(w.from_ns, w.to_ns, w.why) for w in windows["drive"]] == [(S - margin, 2 * S + margin, "taken_late +2")]
    assert [(w.from_ns, w.to_ns, w.why) for w in windows["wheels"]] == [(3 * S - margin, 4 * S + margin, "taken_late +1")]
    assert set(windows) == {"rc", "drive", "wheels"}


def test_a_servo_drivers_loop_behind_in_its_health_makes_a_window(tmp_path: Path) -> None:
    """A servo driver whose health says its loop was 0.17 s behind (a loaded machine held it up: it took a backlog
    of commands late) gets a window from when the loop last turned to HELD_MARGIN_S after; a loop that turns on
    time does not, nor does another kind's slow loop."""
    from u2sa_hw.hil.held_up import plan_windows

    log = McapLogWriter(tmp_path, path=tmp_path / "run.mcap")
    for k, age in enumerate(["0.30", "0.02", "0.17", "0.01"]):   # the first: before the loop first turned
        log.write("U2SA_HEALTH", mux_health("drive", loop_age_s=age, started_us=5).encode(), (k + 1) * S)
        log.write("U2SA_HEALTH", mux_health("gps", loop_age_s="0.90").encode(), (k + 1) * S)
    log.close()
    windows = plan_windows(tmp_path / "run.mcap", kinds={"drive": "pwm_servo", "gps": "nmea_gps"}, devices={},
                           start_ns=S, end_ns=10 * S)
    margin = int(HELD_MARGIN_S * S)
    assert [(w.from_ns, w.to_ns, w.why) for w in windows["drive"]] == [
        (3 * S - 170_000_000 - margin, 3 * S + margin, "its loop 0.17 s behind")]
    assert set(windows) == {"drive"}


def test_from_a_services_first_stopping_health_to_the_end_is_a_window(tmp_path: Path) -> None:
    """The live service took no more input once it was stopping; the replayed one takes the commands recorded
    after that: a servo's writes for them, between its last recorded write and its stop write, are notes."""
    from u2sa_hw.hil.held_up import STOP_WINDOW_END, plan_windows

    log = McapLogWriter(tmp_path, path=tmp_path / "run.mcap")
    for k, status in enumerate(["ok", "ok", "stopping", "stopped"]):
        health = mux_health("drive")
        health.status = status
        log.write("U2SA_HEALTH", health.encode(), (k + 1) * S)
    log.close()
    windows = plan_windows(tmp_path / "run.mcap", kinds={"drive": "pwm_servo"}, devices={}, start_ns=S, end_ns=10 * S)
    assert [(w.from_ns, w.to_ns) for w in windows["drive"]] == [(3 * S - int(HELD_MARGIN_S * S), STOP_WINDOW_END)]
    writes = [Sample(S + k * 40_000_000, "RawPwmWrite", {"duty_ns": 1_500_000 + 1000 * k}) for k in range(60)]
    stop = Sample(4 * S, "RawPwmWrite", {"duty_ns": 1_500_000})
    rec = writes[:50] + [stop]                     # the live driver wrote nothing more once it was stopping
    rep = writes + [stop]                          # the replayed one wrote the later commands too
    r = compare_stream("RAW.throttle [drive]", rec, rep, tolerance=1e-6, edge=0, rate=None, time_tolerance_s=0.5,
                       held=windows["drive"])
    assert r.ok and r.inserted == 0, (r.problems, r.notes)
    assert any("was stopping" in n and "after t=" in n for n in r.notes)
    r = compare_stream("RAW.throttle [drive]", rec, rep, tolerance=1e-6, edge=0, rate=None, time_tolerance_s=0.5)
    assert r.inserted == 10 and not r.ok   # without the window: differences


def edge(k: int, *, late_ns: int = 0) -> bytes:
    rec = t.RawGpioEdge()
    rec.device, rec.line, rec.edge = "rc", 5, k % 2
    rec.kernel_timestamp_ns = k * 10_000_000
    rec.header.timestamp_us = (rec.kernel_timestamp_ns + 1_000_000 + late_ns) // 1000   # tapped 1 ms after, or late
    return rec.encode()


def test_edges_the_live_driver_read_late_make_a_window(tmp_path: Path) -> None:
    log = McapLogWriter(tmp_path, path=tmp_path / "run.mcap")
    for k in range(300):   # 3 s of edges; the driver read the ones at 1.00-1.02 s 80 ms late
        log.write("RAW.rc", edge(k, late_ns=80_000_000 if 100 <= k <= 102 else 0), S + k * 10_000_000)
    log.close()
    windows = late_edge_windows(tmp_path / "run.mcap", {"rc": "rc"}, start_ns=S, end_ns=5 * S)
    margin = int(HELD_MARGIN_S * S)
    assert [(w.from_ns, w.to_ns) for w in windows["rc"]] == [(2 * S - margin, 2 * S + 20_000_000 + margin)]
    # read on time: none
    log = McapLogWriter(tmp_path, path=tmp_path / "quick.mcap")
    for k in range(300):
        log.write("RAW.rc", edge(k), S + k * 10_000_000)
    log.close()
    assert late_edge_windows(tmp_path / "quick.mcap", {"rc": "rc"}, start_ns=S, end_ns=5 * S) == {}
