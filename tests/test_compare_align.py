"""The replay comparison aligns a stream before it diffs it: one missing message is one deletion."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from u2sa_hw.hil.compare_stream import align, compare_stream
from u2sa_hw.hil.compare_values import Sample, Tolerances
from u2sa_hw.hil.compare_report import CompareReport
from u2sa_hw.hil.stream_align import MAX_DP_CELLS


def fix(i: int, *, x: float | None = None, alt: float = 10.0) -> Sample:
    """A GPS-like fix #i at 5 Hz."""
    return Sample(1_000_000_000 + i * 200_000_000, "StateInformation",
                  {"x": float(i) if x is None else x, "y": 2.0 * i, "z": alt, "sensor_name": "gps"})


def compare(rec: list[Sample], rep: list[Sample], *, tolerance: float | Tolerances = 1e-6, edge: int = 1):
    return compare_stream("STATE_INFO [gps]", rec, rep, tolerance=tolerance, edge=edge, rate=None,
                          time_tolerance_s=1)


def test_one_missing_message_in_the_middle_is_one_deletion_with_its_time_and_the_rest_match() -> None:
    rec = [fix(i) for i in range(300)]
    rep = rec[:120] + rec[121:]
    r = compare(rec, rep)
    assert (r.deleted, r.inserted, r.differing, r.matched) == (1, 0, 0, 299)
    assert not r.ok and r.events[0].kind == "deleted" and r.events[0].index == 120
    assert r.events[0].t_ns == rec[120].t_ns
    text = CompareReport(Path("a"), Path("b"), [r], Tolerances(), False, rec[0].t_ns).format()
    assert "recorded #120 at t=24.000 s is missing from the replay" in text
    assert "1 deleted" in text.splitlines()[-1]


def test_one_extra_message_is_one_insertion() -> None:
    rec = [fix(i) for i in range(50)]
    rep = rec[:30] + [fix(30, x=99.0)] + rec[30:]
    r = compare(rec, rep)
    assert (r.inserted, r.deleted, r.differing, r.matched) == (1, 0, 0, 50)


def test_a_changed_setting_is_reported_as_field_differences_not_as_insertions() -> None:
    rec = [fix(i) for i in range(100)]
    rep = [fix(i, alt=12.5) for i in range(100)]
    r = compare(rec, rep)
    assert (r.differing, r.inserted, r.deleted, r.matched) == (100, 0, 0, 0)
    assert set(r.fields) == {"z"} and r.fields["z"].count == 100 and r.fields["z"].max_abs == pytest.approx(2.5)


def test_a_gap_with_a_missing_and_changed_messages_pairs_the_changed_ones_with_their_originals() -> None:
    rec = [fix(i) for i in range(40)]
    # #10 lost, #11..#13 replayed with another altitude: the gap has 4 recorded and 3 replayed messages
    rep = rec[:10] + [fix(i, alt=11.0) for i in (11, 12, 13)] + rec[14:]
    r = compare(rec, rep)
    assert (r.deleted, r.inserted, r.differing, r.matched) == (1, 0, 3, 36)
    assert r.events[0].index == 10 and set(r.fields) == {"z"}


def test_cut_messages_at_the_ends_are_notes_within_edge() -> None:
    rec = [fix(i) for i in range(20)]
    r = compare(rec, rec[1:-1], edge=1)
    assert r.ok and r.matched == 18 and r.notes
    assert not compare(rec, rec[2:], edge=1).ok


def test_floats_equal_within_tolerance_even_across_a_rounding_boundary() -> None:
    rec = [fix(i, x=0.5e-6 * 0.999 + i) for i in range(10)]
    rep = [fix(i, x=0.5e-6 * 1.001 + i) for i in range(10)]
    r = compare(rec, rep, tolerance=1e-6)
    assert r.ok and r.matched == 10


def test_tolerances_per_field_from_a_file(tmp_path: Path) -> None:
    f = tmp_path / "tol.toml"
    f.write_text('default = 1e-6\nignore = ["sensor_name"]\n[fields]\n"z" = 0.5\n')
    tol = Tolerances.load(f)
    assert tol.of("z") == 0.5 and tol.of("x") == 1e-6 and tol.ignore == ("sensor_name",)
    rec = [fix(i) for i in range(10)]
    assert compare(rec, [fix(i, alt=10.25) for i in range(10)], tolerance=tol).ok
    assert not compare(rec, [fix(i, alt=11.0) for i in range(10)], tolerance=tol).ok


@pytest.mark.parametrize("text, expected", [
    ("default = -1\n", "finite number >= 0"),
    ("[fields]\nx = \"big\"\n", "fields.x"),
    ("nope = 1\n", "unknown key"),
    ("default = \n", "not a TOML tolerance file"),
])
def test_a_bad_tolerance_file_names_the_file_and_the_fix(tmp_path: Path, text: str, expected: str) -> None:
    f = tmp_path / "tol.toml"
    f.write_text(text)
    with pytest.raises(ValueError, match=expected) as info:
        Tolerances.load(f)
    assert str(f) in str(info.value)
    with pytest.raises(ValueError, match="cannot read"):
        Tolerances.load(tmp_path / "missing.toml")


def test_json_report_holds_counts_events_and_first_differences() -> None:
    rec = [fix(i) for i in range(30)]
    rep = rec[:5] + rec[6:20] + [fix(i, x=float("inf")) for i in range(20, 30)]
    r = compare(rec, rep)
    report = CompareReport(Path("a.mcap"), Path("b.mcap"), [r], Tolerances(), False, rec[0].t_ns)
    data = json.loads(json.dumps(report.to_dict()))
    s = data["streams"][0]
    assert (s["deleted"], s["different"], data["ok"]) == (1, 10, False)
    assert s["events"][0] == {"kind": "deleted", "index": 5, "t_s": pytest.approx(1.0)}
    assert s["fields"][0]["field"] == "x" and s["fields"][0]["first"]["replayed"] == "inf"
    assert data["summary"].startswith("compare: DIFFERENT 1 of 1 streams")


def test_a_huge_unequal_gap_still_aligns_in_order_without_the_quadratic_search() -> None:
    n = int(MAX_DP_CELLS ** 0.5) + 50
    rec = [fix(i) for i in range(n)]
    rep = [fix(i, alt=1.0) for i in range(n - 3)]
    pairs = align(rec, rep, tolerance=1e-6)
    assert [p.kind for p in pairs].count("differ") == n - 3 and [p.kind for p in pairs].count("deleted") == 3


def rc_mode(i: int, *, pulse_us: int = 1900, blocked_by: str = "") -> Sample:
    """An RC_MODE state #i at 20 Hz."""
    return Sample(1_000_000_000 + i * 50_000_000, "RcMode",
                  {"mode": 2, "pulse_us": pulse_us, "armed": not blocked_by, "blocked_by": blocked_by})


def test_rc_mode_fields_decided_from_the_rest_of_the_system_are_notes_and_its_own_fields_are_differences() -> None:
    rec = [rc_mode(i) for i in range(40)]
    system_only = [rc_mode(i, blocked_by="pre-arm check failed: imu: degraded" if i > 10 else "") for i in range(40)]
    r = compare_stream("RC_MODE [rc]", rec, system_only, tolerance=1e-6, edge=1, rate=None, time_tolerance_s=1)
    assert r.ok and (r.matched, r.differing) == (40, 0), r.problems
    assert any("armed differs in 29" in n and "blocked_by differs in 29" in n for n in r.notes), r.notes
    own = [rc_mode(i, pulse_us=1500) for i in range(40)]
    r = compare_stream("RC_MODE [rc]", rec, own, tolerance=1e-6, edge=1, rate=None, time_tolerance_s=1)
    assert not r.ok and r.differing == 40 and set(r.fields) == {"pulse_us"}
    # the same field names on another channel are the service's own
    r = compare_stream("STATE_INFO [x]", rec, system_only, tolerance=1e-6, edge=1, rate=None, time_tolerance_s=1)
    assert not r.ok and r.differing == 29


def test_an_rc_mode_published_for_a_verdict_change_on_one_side_only_is_a_note_a_timed_one_counts() -> None:
    """Under load the live mux read the other services' health in another order than the recorder wrote it:
    its verdict changed a few messages apart from the replay's, and each change is published at once. Such a
    message on one side only is a note; an extra message that changes no verdict (a timed one) still counts."""
    blocked = "pre-arm check failed: gps: no fix"
    live = [rc_mode(i, pulse_us=1000 + i, blocked_by=blocked if i < 20 else "") for i in range(40)]
    # the replay's verdict cleared after #17 (a change message between two timed ones), the live one at #20
    replay = [rc_mode(i, pulse_us=1000 + i, blocked_by=blocked if i < 18 else "") for i in range(18)]
    replay += [Sample(live[17].t_ns + 10_000_000, "RcMode", {**replay[-1].fields, "armed": True, "blocked_by": ""})]
    replay += [rc_mode(i, pulse_us=1000 + i) for i in range(18, 40)]
    r = compare_stream("RC_MODE [rc]", live, replay, tolerance=1e-6, edge=1, rate=None, time_tolerance_s=1)
    assert r.ok and (r.inserted, r.deleted, r.matched) == (0, 0, 40), (r.problems, r.notes)
    assert any("1 message(s) on one side only, each published for a change of such a verdict" in n for n in r.notes)
    # the same message published again without a verdict change (a timed message the live mux did not send)
    extra = replay[:30] + [Sample(replay[29].t_ns + 10_000_000, "RcMode", dict(replay[29].fields))] + replay[30:]
    r = compare_stream("RC_MODE [rc]", live, extra, tolerance=1e-6, edge=1, rate=None, time_tolerance_s=1)
    assert not r.ok and r.inserted == 1


def test_first_difference_names_the_stream_index_and_fields_or_the_counts() -> None:
    from u2sa_hw.hil.stream_align import first_difference

    a = {"GPS": [("State", {"x": 1.0, "y": 2.0}), ("State", {"x": 3.0, "y": 4.0})]}
    assert first_difference(a, {"GPS": list(a["GPS"])}) == ""
    assert first_difference(a, {"GPS": [a["GPS"][0], ("State", {"x": 3.0, "y": 5.0})]}) == "GPS #1: y 4.0 / 5.0"
    assert first_difference(a, {"GPS": a["GPS"][:1]}) == "GPS: 2 messages against 1"
    assert first_difference(a, {}) == "GPS: 2 messages against 0"
