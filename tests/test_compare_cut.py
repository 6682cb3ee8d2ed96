"""``--compare`` at the cut of a recording (hil/compare.py): a recording that begins or ends inside a GPS
epoch gives a first or last message that holds part of the live one (the live driver had read the
epoch's GGA before the recording started: recorded position and velocity, replayed velocity only). That
is a note naming the stream, the message and the cut. A real difference in the first or last message (a
value) is still a difference, and so is a partial message away from the edges."""

from __future__ import annotations

from u2sa_hw.hil.compare_cuts import begun_after_start
from u2sa_hw.hil.compare_stream import compare_stream
from u2sa_hw.hil.compare_values import Sample
from u2sa_hw.lcmtypes import StateInformation
from u2sa_hw.messages import enumerate_fields

POSITION = ("x", "y", "z", "x_sigma", "y_sigma", "z_sigma")
VELOCITY = ("x_dot", "y_dot", "x_dot_sigma", "y_dot_sigma")


def fix(k: int, *, held: tuple[str, ...] = POSITION + VELOCITY, x: float | None = None) -> Sample:
    """The k-th GPS fix with the fields *held* (values from k), as load_streams gives it."""
    msg = StateInformation()
    msg.header.source = "gps"
    msg.set(**{name: 0.5 + k + (POSITION + VELOCITY).index(name) / 10 for name in held})   # set() marks them present
    if x is not None:
        msg.set(x=x)
    fields = {n: v for n, v in enumerate_fields(msg) if n not in ("header.timestamp_us", "header.sequence")}
    return Sample(1_000_000_000 + k * 200_000_000, "StateInformation", fields)


def stream(n: int = 10) -> list[Sample]:
    return [fix(k) for k in range(n)]


def compare(rec: list[Sample], rep: list[Sample]):
    return compare_stream("STATE_INFO [gps]", rec, rep, tolerance=1e-6, edge=1, rate=None, time_tolerance_s=0.5)


def test_the_fixture_builds_partial_messages() -> None:
    # the presence vector says which fields a message holds: a velocity-only fix leaves x out
    full, vel = fix(0), fix(0, held=VELOCITY)
    assert full.fields["x"] == 0.5 and str(vel.fields["x"]) == "-" and vel.fields["x_dot"] == full.fields["x_dot"]
    assert vel.fields["presence_vector"] != full.fields["presence_vector"]


def test_a_first_epoch_cut_by_the_recording_is_a_note_naming_the_cut() -> None:
    rec = stream()
    rep = [fix(0, held=VELOCITY)] + stream()[1:]   # the replay had only the epoch's VTG
    r = compare(rec, rep)
    assert r.ok, r.problems
    assert (r.differing, r.inserted, r.deleted, r.matched) == (0, 0, 0, 9)
    [note] = [n for n in r.notes if n.startswith("cut:")]
    assert "recorded #0" in note and "start of the stream" in note and "begins inside" in note and "only the recorded one holds x, y, z" in note


def test_a_first_epoch_split_in_two_by_the_cut_is_a_note() -> None:
    rec = stream()
    rep = [fix(0, held=POSITION), fix(0, held=VELOCITY)] + stream()[1:]
    r = compare(rec, rep)
    assert r.ok, r.problems
    assert any(n.startswith("cut:") for n in r.notes), r.notes


def test_a_last_epoch_cut_by_the_recording_is_a_note() -> None:
    rec = stream()
    rep = stream()[:-1] + [fix(9, held=POSITION)]   # the recording ended after the epoch's GGA
    r = compare(rec, rep)
    assert r.ok, r.problems
    [note] = [n for n in r.notes if n.startswith("cut:")]
    assert "recorded #9" in note and "end of the stream" in note


def test_a_real_difference_in_the_first_or_the_last_message_is_still_reported() -> None:
    for index in (0, 9):
        rep = stream()
        rep[index] = fix(index, x=rep[index].fields["x"] + 0.01)   # a driver change: a value, not a cut
        r = compare(stream(), rep)
        assert not r.ok and r.differing == 1 and "x" in r.fields, (index, r.problems, r.notes)
        assert not any(n.startswith("cut:") for n in r.notes)
        # a partial message whose shared values differ is no cut either
        rep[index] = fix(index, held=VELOCITY)
        rep[index].fields["x_dot"] += 0.01
        r = compare(stream(), rep)
        assert not r.ok and r.differing == 1, (index, r.problems, r.notes)


def test_a_partial_message_away_from_the_edges_is_a_difference() -> None:
    rep = stream()
    rep[5] = fix(5, held=VELOCITY)
    r = compare(stream(), rep)
    assert not r.ok and r.differing == 1 and "x" in r.fields, r.problems
    assert not any(n.startswith("cut:") for n in r.notes)


def pwm(k: int, duty: int, *, enabled: bool = True) -> Sample:
    return Sample(1_000_000_000 + k * 20_000_000, "RawPwmWrite",
                  {"device": "pan", "channel": 0, "period_ns": 20_000_000, "duty_ns": duty, "enabled": enabled})


STARTUP = [pwm(0, 0, enabled=False), pwm(1, 1_500_000, enabled=False), pwm(2, 1_500_000)]


def test_a_pwm_stream_recorded_after_its_driver_started_notes_the_replayed_start_up_writes() -> None:
    """A recording begun after the PWM driver started holds no start-up writes; the replayed driver makes
    them again before the first recorded one: a note. A stream that does record them compares them."""
    commands = [pwm(3 + k, 1_500_000 + 10_000 * k) for k in range(6)]
    r = compare_stream("RAW.pan [pan]", commands, STARTUP + commands, tolerance=1e-6, edge=1, rate=None,
                       time_tolerance_s=0.5, started_before=True)
    assert r.ok and (r.matched, r.inserted) == (6, 0), (r.problems, r.notes)
    assert any("3 replayed start-up write(s)" in n for n in r.notes), r.notes
    # without the mark (a recording holding the start-up): the writes beyond the edge are insertions
    r = compare_stream("RAW.pan [pan]", commands, STARTUP + commands, tolerance=1e-6, edge=1, rate=None,
                       time_tolerance_s=0.5)
    assert r.inserted == 2 and not r.ok
    # the mark is read off the recorded stream: its first write already enabled
    assert begun_after_start(commands) and not begun_after_start(STARTUP + commands)


def stamped(k: int, *, published_after_ns: int = 1_000_000) -> Sample:
    """Compass heading k: read at input time T_k, published 1 ms later (the recorded header) -- a replay on the
    device clock stamps it with T_k, the recorded input time."""
    read_ns = 1_000_000_000 + k * 100_000_000
    return Sample(read_ns + published_after_ns + 500_000, "StateInformation", {"yaw": float(k)},
                  read_ns + published_after_ns)


def test_replayed_messages_of_input_read_after_the_last_recorded_output_are_the_cut_at_the_end() -> None:
    """The recorder stopped after tapping the compass's last chunk (two sentences read at once on a loaded
    machine) but before the live driver published their headings: the replay publishes both, stamped with that
    chunk's recorded read time, inside the recording's last second and after its last recorded heading."""
    rec = [stamped(k) for k in range(10)]
    chunk_read = stamped(10, published_after_ns=0).stamp_ns
    rep = [stamped(k, published_after_ns=0) for k in range(10)] + [
        Sample(0, "StateInformation", {"yaw": yaw}, chunk_read) for yaw in (10.0, 11.0)]
    end = chunk_read + 300_000   # the recorder logged the chunk's tap, then stopped
    r = compare_stream("STATE_INFO [compass]", rec, rep, tolerance=1e-6, edge=0, rate=None, time_tolerance_s=0.5,
                       recording_end_ns=end)
    assert r.ok and r.inserted == 0, (r.problems, r.notes)
    assert any("the cut at the end" in n for n in r.notes)
    # the recording went on for 2 s after that input with nothing from the stream: the live driver did not
    # publish them, the replay does: a difference
    r = compare_stream("STATE_INFO [compass]", rec, rep, tolerance=1e-6, edge=0, rate=None, time_tolerance_s=0.5,
                       recording_end_ns=chunk_read + 2_000_000_000)
    assert r.inserted == 2 and not r.ok
    # a replayed message stamped on the replaying machine's clock (the RC mux's) is never taken for the cut
    late = [Sample(0, "StateInformation", {"yaw": 10.0}, end + 3600 * 1_000_000_000)]
    r = compare_stream("STATE_INFO [compass]", rec, rep[:10] + late, tolerance=1e-6, edge=0, rate=None,
                       time_tolerance_s=0.5, recording_end_ns=end)
    assert r.inserted == 1 and not r.ok


def odometry(k: int, speed: float) -> Sample:
    return Sample(1_000_000_000 + k * 20_000_000, "StateInformation", {"x_dot": speed, "psi_dot": 0.0})


def test_a_stream_flowing_as_the_recording_began_settles_within_a_second() -> None:
    """A recording begun while the wheels turned: the live odometry's first pair held a wheel sample read before
    the cut, the replay pairs that wheel's next one, and the pairs alternate for a while. What differs within a
    second of the start is the cut; the same difference later, or in a stream that began after the recording
    did, counts."""
    from u2sa_hw.hil.compare_cuts import flowing_at_start

    rec = [odometry(k, 2.0 + k / 100) for k in range(50)]
    rep = [odometry(0, 2.09), odometry(1, 1.97)] + rec[2:]
    assert flowing_at_start(rec, rec[0].t_ns - 10_000_000) and not flowing_at_start(rec, rec[0].t_ns - 1_000_000_000)
    kwargs = dict(tolerance=1e-6, edge=0, rate=None, time_tolerance_s=0.5)
    r = compare_stream("STATE_INFO [wheels]", rec, rep, flowing=True, **kwargs)
    assert r.ok and r.matched == 48, (r.problems, r.notes)
    assert any("of the stream's start: the recording began while it flowed" in n for n in r.notes)
    assert not compare_stream("STATE_INFO [wheels]", rec, rep, **kwargs).ok
    settling = [odometry(0, 2.09), odometry(1, 1.97)] + rec[2:20] + [odometry(20, 2.3)] + rec[21:]
    assert compare_stream("STATE_INFO [wheels]", rec, settling, flowing=True, **kwargs).ok   # 0.4 s in: settling
    later = list(rec)
    later[45] = odometry(45, 9.0)   # 0.9 s in: still the first second
    assert compare_stream("STATE_INFO [wheels]", rec, later, flowing=True, **kwargs).ok
    longer = [odometry(k, 2.0 + k / 100) for k in range(100)]
    late = longer[:70] + [odometry(70, 9.0)] + longer[71:]   # 1.4 s in: a difference
    assert compare_stream("STATE_INFO [wheels]", longer, late, flowing=True, **kwargs).differing == 1


def test_a_stream_that_begins_after_the_recording_is_not_flowing_for_compare_logs(tmp_path) -> None:
    """Without a window, the recording began at the log's first message of any channel (as a replay's plan takes
    it), not at the first compared one: a GPS stream that begins 2 s after the log's first health is no stream
    caught flowing, and a fix missing 0.4 s into it is a deletion (it was a settling note, as if flowing)."""
    from u2sa_hw import lcmtypes as t
    from u2sa_hw.hil.compare import compare_logs
    from u2sa_hw.recording.mcap_log import McapLogWriter

    def log(path, skip: int | None):
        writer = McapLogWriter(tmp_path, path=path)
        health = t.Health()
        health.name, health.status = "gps", "ok"
        writer.write("U2SA_HEALTH", health.encode(), 1_000_000_000)
        for k in range(10):
            if k == skip:
                continue
            msg = StateInformation()
            msg.header.source, msg.sensor_name = "gps", "gps"
            msg.set(x=float(k), y=2.0 * k)
            writer.write("STATE_INFO", msg.encode(), 3_000_000_000 + k * 200_000_000)
        writer.close()
        return path

    recorded, replayed = log(tmp_path / "rec.mcap", None), log(tmp_path / "rep.mcap", 2)
    report = compare_logs(recorded, replayed, services={"gps"}, rate=None).to_dict()
    [gps] = report["streams"]
    assert (gps["deleted"], gps["matched"], gps["ok"]) == (1, 9, False), gps
