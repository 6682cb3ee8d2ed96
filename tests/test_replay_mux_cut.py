"""A recording (or a ``--start`` window) that begins with the RC mux armed in autonomous mode: the pilot armed it
through manual before the cut, which no replay of the log can reproduce (a mux coming out of "no signal" with the
switch at autonomous stays disarmed until the pilot goes through manual). The plan leaves the mux out with a note
and the actuators get its recorded RC_MODE (hil/replay_plan.py, ``autonomy_armed_at_start``; issue 24: a
``u2sa record`` started while the vehicle drove under autonomy replayed ``RAW.rc [rc] only in the replay``)."""

from __future__ import annotations

from pathlib import Path

from u2sa_hw import lcmtypes as t
from u2sa_hw.drivers.rc_mux.pulse import MODE_AUTONOMOUS, MODE_MANUAL, MODE_NO_SIGNAL
from u2sa_hw.hil.replay_plan import autonomy_armed_at_start
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
