"""The pre-arm verdict is kept for every time between the age limits around the one it was judged at
(u2sa_hw/safety/prearm.py ``PrearmChecks.verdict``): the RC mux asks at each edge's stamp, and the edges
of a frame are stamped a little before its loop's last look at the clock, so a verdict that held only
forward was judged afresh at every loop turn. Kept or not, it is the verdict a fresh judgement gives,
backwards in time too."""

from __future__ import annotations

import random
from pathlib import Path

from test_prearm import GOOD_GPS, checks_for, estimate, feed_good, health


def test_a_verdict_stands_for_an_earlier_time_with_no_age_limit_between(tmp_path: Path) -> None:
    checks = checks_for(tmp_path, {"health_timeout_s": 3.0, "estimator": {"max_estimate_age_s": 0}})
    feed_good(checks, 100.0)
    at_look = checks.verdict(100.5, rc_link_ok=True, failsafe_reason="")
    # an edge stamped 5 ms before the look, then the next look: the same verdict, the very same object
    assert checks.verdict(100.495, rc_link_ok=True, failsafe_reason="") is at_look
    assert checks.verdict(100.52, rc_link_ok=True, failsafe_reason="") is at_look
    assert checks.evaluate(100.495, rc_link_ok=True, failsafe_reason="") == list(at_look) == []
    # past the health timeout, then back before it: each time judged as it stands then
    late = checks.verdict(103.5, rc_link_ok=True, failsafe_reason="")
    assert late and "no health for over 3 s" in late[0].reason
    assert checks.verdict(102.9, rc_link_ok=True, failsafe_reason="") == ()


def test_a_kept_verdict_is_the_fresh_one_when_time_goes_back_and_forth(tmp_path: Path) -> None:
    checks = checks_for(tmp_path, {"estimator": {"max_estimate_age_s": 0.5}, "health_timeout_s": 1.0})
    rnd = random.Random(11)
    now, kept, asked = 100.0, 0, 0
    for _ in range(4000):
        roll = rnd.random()
        if roll < 0.03:
            feed_good(checks, now, skip=tuple(n for n in checks.watched if rnd.random() < 0.3))
        elif roll < 0.05:
            checks.on_health(health("gps", **{**GOOD_GPS, "fix_type": rnd.choice(["3D", "2D"])}), now)
        elif roll < 0.07:
            checks.on_estimate(estimate(x_sigma=rnd.choice([0.5, 9.0])), now)
        link = rnd.random() > 0.02
        before = checks._memo
        got = checks.verdict(now, rc_link_ok=link, failsafe_reason="")
        kept += checks._memo is before
        asked += 1
        assert list(got) == checks._judge_all(now, rc_link_ok=link, failsafe_reason=""), now
        # forward and back (an edge stamped before the last look), onto and around the limits
        now += rnd.choice([0.0, 0.001, 0.02, 0.25, 0.5, 1.0, 1e-6, 0.4999995, 0.9999995,
                           -0.001, -0.005, -0.02, -1e-6, -0.4999995])
    assert 0 < kept < asked
