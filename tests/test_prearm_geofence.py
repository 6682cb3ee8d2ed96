"""The pre-arm check ``geofence`` (u2sa_hw/safety/prearm_geofence.py) as pure logic: an injected clock,
STATE_ESTIMATE messages built here, profiles written to tmp_path. The RC mux asks the same checks while
autonomous, so a breach there is a lost check (test_safety_chain.py covers that reaction end to end)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import tomli_w

from test_prearm import OK, SERVICES, feed_good, health
from u2sa_hw import lcmtypes as t
from u2sa_hw.messages import STATE_FIELDS  # noqa: F401 - installs the presence setters
from u2sa_hw.safety.prearm import PrearmChecks
from u2sa_hw.profile.vehicle import ProfileError
from u2sa_hw.profile.loader import load_profile

FENCE = {"polygons": [{"name": "field", "local": [[-10, -10], [30, -10], [30, 35], [-10, 35]]}],
         "circles": [{"name": "pond", "inclusion": False, "local_center": [10, 12], "radius_m": 3}]}


def checks(tmp_path: Path, *, geofence: Any = FENCE, prearm: dict[str, Any] | None = None) -> PrearmChecks:
    data: dict[str, Any] = {"vehicle": {"name": "t"}, "services": SERVICES}
    if geofence is not None:
        data["geofence"] = geofence
    if prearm is not None:
        data["safety"] = {"prearm": prearm}
    path = tmp_path / "vehicle.toml"
    path.write_text(tomli_w.dumps(data))
    return PrearmChecks.from_profile(load_profile(path))


def at(x: float, y: float, *, source: str = "estimator") -> t.StateInformation:
    msg = t.StateInformation()
    msg.header.source = msg.sensor_name = source
    msg.set(x=x, y=y, x_sigma=0.3, y_sigma=0.3, psi=0.0, psi_sigma=0.01)
    return msg


def failures(c: PrearmChecks, now: float) -> list[str]:
    return [f.reason for f in c.evaluate(now, **OK) if f.check == "geofence"]


def test_the_check_is_on_whenever_there_is_a_fence_and_wants_the_estimate(tmp_path: Path) -> None:
    c = checks(tmp_path)
    assert c.table.geofence is not None and c.table.geofence.service == "estimator"
    assert "geofence" in c.table.enabled() and c.needs_estimate
    assert "geofence (estimator's position inside 'field', 'pond')" in c.describe()
    assert checks(tmp_path, geofence=None).table.geofence is None


def test_inside_passes_outside_and_in_an_exclusion_fail_naming_the_area(tmp_path: Path) -> None:
    c = checks(tmp_path)
    feed_good(c, 10.0)
    c.on_estimate(at(0.0, 0.0), 10.0)
    assert c.evaluate(10.0, **OK) == []
    c.on_estimate(at(31.0, 0.0), 10.1)
    assert failures(c, 10.1) == ["geofence: outside inclusion polygon 'field'; drive back inside in manual"]
    assert c.summary()["prearm_failed"] == "geofence"
    c.on_estimate(at(10.0, 13.0), 10.2)
    assert failures(c, 10.2) == ["geofence: inside exclusion circle 'pond'; drive back inside in manual"]
    c.on_estimate(at(5.0, 5.0), 10.3)
    assert failures(c, 10.3) == []


def test_no_position_or_an_old_one_fails_safe(tmp_path: Path) -> None:
    c = checks(tmp_path, prearm={"geofence": {"max_position_age_s": 0.5}})
    for name in c.watched:
        c.on_health(health(name), 10.0)
    assert failures(c, 10.0) == ["geofence: no position from estimator yet: cannot tell the vehicle is inside the "
                                 "fence (fail safe)"]
    c.on_estimate(at(0.0, 0.0), 10.0)
    assert failures(c, 10.4) == []
    assert failures(c, 10.6) == ["geofence: no position from estimator for over 0.5 s: cannot tell the vehicle is "
                                 "inside the fence (fail safe)"]
    no_position = t.StateInformation()
    no_position.header.source = "estimator"
    c.on_estimate(no_position, 10.7)
    assert "no position from estimator yet" in failures(c, 10.7)[0]


def test_another_estimators_position_is_not_judged(tmp_path: Path) -> None:
    c = checks(tmp_path)
    c.on_estimate(at(0.0, 0.0), 10.0)
    c.on_estimate(at(99.0, 0.0, source="other"), 10.1)
    assert failures(c, 10.1) == []


def test_a_kept_verdict_turns_at_the_position_age_limit(tmp_path: Path) -> None:
    c = checks(tmp_path, prearm={"geofence": {"max_position_age_s": 1.0}, "estimator": {"max_estimate_age_s": 0}})
    feed_good(c, 10.0)
    c.on_estimate(at(0.0, 0.0), 10.0)
    first = c.verdict(10.5, **OK)
    assert c.verdict(10.9, **OK) is first   # same evidence, inside the span: the same verdict object
    assert [f.check for f in c.verdict(11.1, **OK)] == ["geofence"]


@pytest.mark.parametrize("geofence, prearm, words", [
    (FENCE, {"geofence": False}, "cannot be false while the profile has a \\[geofence\\]"),
    (None, {"geofence": True}, "no \\[geofence\\] table"),
    (FENCE, {"geofence": {"service": "gps"}}, "names service 'gps' of kind gps_nmea"),
    (FENCE, {"geofence": {"max_position_age_s": 1e9}}, "out of range"),
])
def test_a_bad_geofence_check_is_refused_with_the_fix(tmp_path: Path, geofence: Any, prearm: dict[str, Any],
                                                      words: str) -> None:
    with pytest.raises(ProfileError, match=words):
        checks(tmp_path, geofence=geofence, prearm=prearm)


def test_a_fence_without_an_estimator_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "vehicle.toml"
    path.write_text(tomli_w.dumps({"vehicle": {"name": "t"}, "services": {"rc": {"kind": "rc_mux"}},
                                   "geofence": FENCE}))
    with pytest.raises(ProfileError, match="no enabled state_estimator service"):
        PrearmChecks.from_profile(load_profile(path))
