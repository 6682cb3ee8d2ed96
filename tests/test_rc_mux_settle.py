"""The RC mux skips the settle after an event that changed nothing it reads (drivers/rc_mux/state.py
``_settle``): most edges change nothing, and the pre-arm checks, the enable line and the RcMode it
publishes were worked out again after every one. Skipping must not change a message: the recorded
input of tests/test_rc_mux_timing.py (manual, autonomy granted, a failsafe raised and cleared, a signal
loss, and a select read-back that disagrees while the line is high) gives the very same messages with
the skip and with a settle in full after every event."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from test_rc_mux_timing import all_at_once, in_uneven_chunks, run_driver, socket_dir  # noqa: F401 - a fixture

from u2sa_hw.drivers.rc_mux.state import MuxState


def _counting(monkeypatch: pytest.MonkeyPatch, *, skip: bool) -> dict[str, int]:
    """Count the settles and those run in full; without *skip* every settle runs in full."""
    counts = {"settles": 0, "full": 0}
    settle, check_prearm = MuxState._settle, MuxState._check_prearm

    def counted_settle(self: MuxState, at_ns: int | None) -> None:
        counts["settles"] += 1
        settle(self, at_ns)

    def counted_check(self: MuxState, verdict: Any) -> None:
        counts["full"] += 1
        check_prearm(self, verdict)

    monkeypatch.setattr(MuxState, "_settle", counted_settle)
    monkeypatch.setattr(MuxState, "_check_prearm", counted_check)
    if not skip:
        monkeypatch.setattr(MuxState, "_settle_inputs", lambda self, verdict, failsafe: None)
    return counts


@pytest.mark.parametrize("feed", [all_at_once, in_uneven_chunks], ids=["all at once", "uneven"])
def test_skipping_a_settle_that_changes_nothing_changes_no_message(tmp_path: Path, socket_dir: Path,  # noqa: F811
                                                                    monkeypatch: pytest.MonkeyPatch,
                                                                    feed: Any) -> None:
    runs, counts = {}, {}
    for skip in (False, True):
        with monkeypatch.context() as patch:
            counts[skip] = _counting(patch, skip=skip)
            sub = tmp_path / f"skip-{skip}"
            sub.mkdir()
            runs[skip] = run_driver(sub, socket_dir, feed)
    full, skipped = runs[False], runs[True]
    assert len(skipped) == len(full)
    for i, (a, b) in enumerate(zip(full, skipped)):
        assert a == b, f"message {i}: {b} with the skip, {a} with every settle in full"
    # in full every time without the skip; with it, far fewer (the edges of a steady frame change nothing)
    assert counts[False]["full"] == counts[False]["settles"]
    assert counts[True]["full"] < counts[True]["settles"] / 2
