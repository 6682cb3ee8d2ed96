"""A recording (or a ``--start`` window) that begins with the RC mux armed in autonomous mode: the pilot armed it
through manual before the cut, which no replay of the log can reproduce (a mux coming out of "no signal" with the
switch at autonomous stays disarmed until the pilot goes through manual). The plan leaves the mux out with a note
and the actuators get its recorded RC_MODE (hil/replay_cut.py, ``autonomy_armed_at_start``; issue 24: a
``u2sa record`` started while the vehicle drove under autonomy replayed ``RAW.rc [rc] only in the replay``)."""

from __future__ import annotations

from pathlib import Path

from u2sa_hw import lcmtypes as t
from u2sa_hw.drivers.rc_mux.pulse import MODE_AUTONOMOUS, MODE_MANUAL, MODE_NO_SIGNAL
from u2sa_hw.hil.compare_values import Sample
from u2sa_hw.hil.replay_cut import autonomy_armed_at_start
from u2sa_hw.recording.log_reader import LogFile
from u2sa_hw.recording.mcap_log import McapLogWriter

S = 1_000_000_000


def rc_mode(mode: int, *, armed: bool, source: str = "rc") -> bytes:
    msg = t.RcMode()
    msg.header.source, msg.mode, msg.armed = source, mode, armed
    msg.autonomy_enabled = armed and mode == MODE_AUTONOMOUS
    return msg.encode()


def log_of(path: Path, modes: list[tuple[int, bool]], *, other_first: bool = False) -> LogFile:
    log = McapLogWriter(path.parent, path=path)
    if other_first:   # another mux's message first: only the replayed service's own count
        log.write("RC_MODE", rc_mode(MODE_NO_SIGNAL, armed=False, source="rc2"), S // 2)
    for k, (mode, armed) in enumerate(modes):
        log.write("RC_MODE", rc_mode(mode, armed=armed), (k + 1) * S)
    log.close()
    return LogFile(path)


def test_only_a_first_rc_mode_armed_in_autonomous_mode_is_a_mux_armed_before_the_cut(tmp_path: Path) -> None:
    drive = log_of(tmp_path / "drive.mcap", [(MODE_AUTONOMOUS, True), (MODE_MANUAL, True)], other_first=True)
    assert autonomy_armed_at_start(drive, "rc", start_ns=0)
    # the replayed mux comes out of "no signal" and arms itself in manual, as the live one did
    assert not autonomy_armed_at_start(log_of(tmp_path / "up.mcap", [(MODE_NO_SIGNAL, False), (MODE_AUTONOMOUS, True)]),
                                       "rc", start_ns=0)
    assert not autonomy_armed_at_start(log_of(tmp_path / "manual.mcap", [(MODE_MANUAL, True)]), "rc", start_ns=0)
    # autonomous but not armed (switch to manual to re-arm): the replayed mux is not armed either
    assert not autonomy_armed_at_start(log_of(tmp_path / "refused.mcap", [(MODE_AUTONOMOUS, False)]), "rc",
                                       start_ns=0)
    # a --start window that begins after the pilot armed and engaged
    later = log_of(tmp_path / "later.mcap", [(MODE_NO_SIGNAL, False), (MODE_MANUAL, True), (MODE_AUTONOMOUS, True)])
    assert not autonomy_armed_at_start(later, "rc", start_ns=0)
    assert autonomy_armed_at_start(later, "rc", start_ns=3 * S)
    assert not autonomy_armed_at_start(later, "other", start_ns=0)   # no message of that service at all


def mode_sample(k: int, mode: int, steering: int) -> Sample:
    return Sample(S + k * 40_000_000, "RcMode", {"mode": mode, "armed": mode == MODE_MANUAL,
                                                 "pulse_us": (1500, steering, 1000)})


def test_a_recording_begun_after_the_mux_decided_notes_the_replayed_muxs_decision_start_up() -> None:
    """Begun while the pilot drove in manual: the replayed mux comes out of "no signal" and needs its debounce
    frames (its first RC_MODE say "no signal"), and requests its enable line low once, which the recording holds
    none of. Those are notes; the same replayed stream against a recording that begins at "no signal" differs."""
    from u2sa_hw.hil.compare_cuts import mux_decided_before
    from u2sa_hw.hil.compare_stream import compare_stream

    rec = [mode_sample(k, MODE_MANUAL, 1500 + 10 * k) for k in range(20)]
    rep = [mode_sample(k, MODE_NO_SIGNAL, 0) for k in range(3)] + rec
    assert mux_decided_before(rec) and not mux_decided_before(rep)
    kwargs = dict(tolerance=1e-6, edge=0, rate=None, time_tolerance_s=0.5)
    r = compare_stream("RC_MODE [rc]", rec, rep, decided_before=True, **kwargs)
    assert r.ok and r.matched == 20, (r.problems, r.notes)
    assert any("while the replayed mux decided its mode" in n for n in r.notes)
    assert not compare_stream("RC_MODE [rc]", rec, rep, **kwargs).ok
    # the same replayed mux's start later in the stream (a signal loss the live one did not have) still counts
    late = rec[:10] + [mode_sample(10, MODE_NO_SIGNAL, 0)] + rec[10:]
    assert not compare_stream("RC_MODE [rc]", rec, late, decided_before=True, **kwargs).ok
    write = mode_sample(0, MODE_MANUAL, 0)
    r = compare_stream("RAW.rc [rc]", [], [write], decided_before=True, **kwargs)
    assert r.ok and "start-up" in r.notes[0]
    assert not compare_stream("RAW.rc [rc]", [], [write], **kwargs).ok
