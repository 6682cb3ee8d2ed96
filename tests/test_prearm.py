"""Pre-arm checks (u2sa_hw/safety/prearm.py) as pure logic: an injected clock, Health and STATE_ESTIMATE
messages built here, and profiles parsed from real files (the examples and ones written to tmp_path)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
import tomli_w

from u2sa_hw import lcmtypes as t
from u2sa_hw.service.health import set_details
from u2sa_hw.messages import STATE_FIELDS  # noqa: F401 - installs the presence setters
from u2sa_hw.safety.prearm import CheckFailure, PrearmChecks
from u2sa_hw.profile.vehicle import ProfileError
from u2sa_hw.profile.loader import load_profile

REPO = Path(__file__).resolve().parent.parent
ROVER = REPO / "examples" / "ground_vehicle" / "vehicle.toml"
BOAT = REPO / "examples" / "boat" / "vehicle.toml"
OK = {"rc_link_ok": True, "failsafe_reason": ""}

SERVICES = {
    "gps": {"kind": "gps_nmea"},
    "imu": {"kind": "imu_mpu9250"},
    "estimator": {"kind": "state_estimator"},
    "world": {"kind": "world_modeler"},
    "planner": {"kind": "path_planner"},
    "rc": {"kind": "rc_mux"},
    "pan": {"kind": "pwm_servo", "required": False},
    "recorder": {"kind": "recorder", "enabled": False},
}


def write_profile(tmp_path: Path, prearm: dict[str, Any] | None = None, *,
                  services: dict[str, Any] | None = None) -> Path:
    data: dict[str, Any] = {"vehicle": {"name": "testrover"}, "services": services or SERVICES}
    if prearm is not None:
        data["safety"] = {"prearm": prearm}
    path = tmp_path / "vehicle.toml"
    path.write_text(tomli_w.dumps(data))
    return path


def checks_for(tmp_path: Path, prearm: dict[str, Any] | None = None, **kwargs: Any) -> PrearmChecks:
    return PrearmChecks.from_profile(load_profile(write_profile(tmp_path, prearm, **kwargs)))


def health(name: str, status: str = "ok", *, last_error: str = "", **details: Any) -> t.Health:
    msg = t.Health()
    msg.name, msg.status, msg.last_error = name, status, last_error
    msg.header.source = name
    set_details(msg, details)
    return msg


GOOD_GPS = {"fix": True, "fix_type": "3D", "satellites": 9, "h_sigma_m": "0.71", "data": "ok",
            "last_data_age_s": "0.10"}


def estimate(*, x_sigma: float | None = 0.5, y_sigma: float | None = 0.5, psi_sigma: float | None = 0.01,
             position: bool = True, heading: bool = True, source: str = "estimator") -> t.StateInformation:
    msg = t.StateInformation()
    msg.header.source = msg.sensor_name = source
    if position:
        msg.set(x=1.0, y=2.0)
        if x_sigma is not None:
            msg.set(x_sigma=x_sigma)
        if y_sigma is not None:
            msg.set(y_sigma=y_sigma)
    if heading:
        msg.set(psi=0.3)
        if psi_sigma is not None:
            msg.set(psi_sigma=psi_sigma)
    return msg


def feed_good(checks: PrearmChecks, now: float, *, skip: tuple[str, ...] = ()) -> None:
    """Every watched service healthy at *now*, and a converged estimate."""
    good = {"gps": GOOD_GPS, "imu": {"calibrated": True, "calibration": "calibrated"},
            "estimator": {"position_sigma_m": "0.7", "heading_sigma_deg": "0.6"}}
    for name in checks.watched - set(skip):
        checks.on_health(health(name, **good.get(name, {})), now)
    if "estimator" not in skip:
        checks.on_estimate(estimate(), now)


def reasons(failures: list[CheckFailure]) -> list[str]:
    return [f.reason for f in failures]


# -- the table and its defaults --------------------------------------------------------------
def test_defaults_come_from_the_rover_profiles_service_kinds() -> None:
    checks = PrearmChecks.from_profile(load_profile(ROVER))
    table = checks.table
    assert table.gps is not None and table.gps.service == "gps" and table.gps.max_sigma_m == 5.0
    assert table.estimator is not None and table.estimator.service == "estimator"
    assert table.imu is not None and table.imu.services == ("imu",)
    assert table.rc_link and table.no_failsafe and table.health_timeout_s == 3.0
    # required: every enabled, required service not judged by its own check and not the RC mux;
    # pan is required = false, the recorder disabled.
    assert table.required_services is not None
    assert table.required_services.services == ("compass", "wheels", "mission", "world", "planner", "control", "hsm")
    assert table.enabled() == ("no_failsafe", "rc_link", "gps", "imu", "estimator", "geofence", "required_services")
    assert table.geofence is not None and table.geofence.service == "estimator"   # the rover's yard
    assert checks.needs_estimate


def test_defaults_come_from_the_boat_profiles_service_kinds() -> None:
    table = PrearmChecks.from_profile(load_profile(BOAT)).table
    assert table.gps is not None and table.gps.service == "gps"
    assert table.imu is not None and table.imu.services == ("imu",)   # a BNO055: any imu_* kind
    assert table.required_services is not None and "thrusters" in table.required_services.services
    assert "rc" not in table.required_services.services


@pytest.mark.parametrize("profile", sorted((REPO / "examples").glob("*/vehicle.toml")), ids=lambda p: p.parent.name)
def test_every_example_profile_parses_with_every_check_on(profile: Path) -> None:
    table = PrearmChecks.from_profile(load_profile(profile)).table
    fenced = ("geofence",) if table.geofence is not None else ()   # the ground vehicle has a fence
    assert table.enabled() == ("no_failsafe", "rc_link", "gps", "imu", "estimator", *fenced, "required_services")


def test_a_profile_without_a_gps_or_imu_has_those_checks_off(tmp_path: Path) -> None:
    services = {k: v for k, v in SERVICES.items() if k not in ("gps", "imu")}
    table = checks_for(tmp_path, services=services).table
    assert table.gps is None and table.imu is None and table.estimator is not None


def test_every_check_can_be_turned_off_and_then_never_fails(tmp_path: Path) -> None:
    off = {"gps": False, "imu": False, "estimator": False, "required_services": False, "rc_link": False,
           "no_failsafe": False}
    checks = checks_for(tmp_path, off)
    assert checks.table.enabled() == () and checks.watched == frozenset()
    assert checks.evaluate(0.0, rc_link_ok=False, failsafe_reason="hsm: gps failed") == []
    assert not checks.needs_estimate


def test_tables_change_bounds_and_services(tmp_path: Path) -> None:
    services = {**SERVICES, "gps2": {"kind": "gps_nmea"}, "imu2": {"kind": "imu_bno055"}}
    prearm = {"gps": {"service": "gps2", "max_sigma_m": 2}, "imu": {"services": ["imu2"]},
              "estimator": {"max_estimate_age_s": 0}, "required_services": {"ignore": ["world"],
                                                                            "allow_degraded": ["planner"]},
              "health_timeout_s": 2}
    table = checks_for(tmp_path, prearm, services=services).table
    assert table.gps is not None and (table.gps.service, table.gps.max_sigma_m) == ("gps2", 2.0)
    assert table.imu is not None and table.imu.services == ("imu2",)
    assert table.health_timeout_s == 2.0
    assert table.required_services is not None
    # gps and imu are not judged by the gps/imu checks here, so they count as required services
    assert table.required_services.services == ("gps", "imu", "planner")
    assert table.required_services.allow_degraded == ("planner",)


@pytest.mark.parametrize("prearm, key, fix", [
    ({"gsp": True}, "'gsp'", "known:"),
    ({"gps": {"max_sigma": 5.0}}, "'gps.max_sigma'", "known: max_sigma_m, service"),
    ({"gps": {"service": "gps9"}}, "'gps.service'", "not in the profile (services: gps, imu"),
    ({"gps": {"service": "world"}}, "'gps.service'", "kind world_modeler"),
    ({"imu": {"services": ["recorder"]}}, "'imu.services'", "disabled (enabled = false)"),
    ({"imu": {"services": ["gps"]}}, "'imu.services'", "imu_* service"),
    ({"imu": {"services": []}}, "'imu.services'", "set imu = false"),
    ({"gps": {"max_sigma_m": "five"}}, "'gps.max_sigma_m'", "must be a number > 0 (m), got 'five'"),
    ({"gps": {"max_sigma_m": 0}}, "'gps.max_sigma_m'", "e.g. gps = { max_sigma_m = 5.0 }"),
    ({"estimator": {"max_estimate_age_s": -1}}, "'estimator.max_estimate_age_s'", "must be a number >= 0"),
    ({"health_timeout_s": True}, "'health_timeout_s'", "e.g. health_timeout_s = 3.0"),
    ({"rc_link": "yes"}, "'rc_link'", "must be true or false"),
    ({"gps": "on"}, "'gps'", "must be true, false or a table"),
    ({"required_services": {"ignore": ["nobody"]}}, "'required_services.ignore'", "not in the profile"),
    ({"required_services": {"allow_degraded": "planner"}}, "'required_services.allow_degraded'", "a list"),
])
def test_a_bad_table_is_one_line_naming_the_file_the_key_and_the_fix(tmp_path: Path, prearm: dict[str, Any],
                                                                     key: str, fix: str) -> None:
    path = write_profile(tmp_path, prearm)
    with pytest.raises(ProfileError) as err:
        PrearmChecks.from_profile(load_profile(path))
    text = str(err.value)
    assert "\n" not in text
    assert text.startswith(f"{path} [safety.prearm]: {key}")
    assert fix in text


def test_a_check_asked_for_whose_service_kind_the_profile_lacks_is_refused(tmp_path: Path) -> None:
    services = {k: v for k, v in SERVICES.items() if k != "gps"}
    with pytest.raises(ProfileError, match=r"'gps' is on, but the profile has no enabled gps_nmea service.*"
                                           r"gps = false"):
        checks_for(tmp_path, {"gps": {"max_sigma_m": 3.0}}, services=services)


# -- judgement -------------------------------------------------------------------------------------
def test_a_healthy_vehicle_passes_and_summary_says_so(tmp_path: Path) -> None:
    checks = checks_for(tmp_path)
    assert checks.summary()["prearm"] == "not evaluated yet"
    feed_good(checks, 10.0)
    assert checks.evaluate(10.2, **OK) == []
    assert checks.summary() == {"prearm": "ok", "prearm_failed": "",
                                "prearm_checks": "no_failsafe,rc_link,gps,imu,estimator,required_services"}


def test_nothing_heard_yet_names_each_silent_service(tmp_path: Path) -> None:
    failures = checks_for(tmp_path).evaluate(0.0, **OK)
    assert reasons(failures) == ["gps: no health yet (is it running?)", "imu: no health yet (is it running?)",
                                 "estimator: no health yet (is it running?)",
                                 "required service world: no health yet (is it running?)",
                                 "required service planner: no health yet (is it running?)"]


def test_failsafe_and_rc_link_come_first_with_their_reasons(tmp_path: Path) -> None:
    checks = checks_for(tmp_path)
    feed_good(checks, 0.0)
    failures = checks.evaluate(0.1, rc_link_ok=False, failsafe_reason="hsm: required service gps failed")
    assert failures == [CheckFailure("no_failsafe", "failsafe held: hsm: required service gps failed"),
                        CheckFailure("rc_link", "rc_link: no valid RC signal")]
    assert checks.summary()["prearm"] == "failsafe held: hsm: required service gps failed"
    assert checks.summary()["prearm_failed"] == "no_failsafe,rc_link"
    assert checks.evaluate(0.2, **OK) == []


@pytest.mark.parametrize("details, reason", [
    ({"fix": False, "fix_type": "2D", "satellites": 7}, "gps: no 3D fix (fix type 2D, 7 satellites)"),
    ({"fix": False, "fix_type": "no fix", "satellites": 3}, "gps: no 3D fix (no fix, 3 satellites)"),
    ({"fix_type": "3D", "h_sigma_m": "7.25", "satellites": 5}, "gps: horizontal sigma 7.2 m > 5 m (5 satellites)"),
    ({"fix_type": "3D", "h_sigma_m": ""}, "gps: horizontal sigma unknown (the receiver sends neither GST nor HDOP)"),
    ({"data": "none yet", "last_data_age_s": ""}, "gps: no data from the receiver yet"),
])
def test_gps_fails_with_the_named_reason_and_recovers(tmp_path: Path, details: dict[str, Any], reason: str) -> None:
    checks = checks_for(tmp_path)
    feed_good(checks, 0.0)
    feed_good(checks, 0.5, skip=("gps",))
    checks.on_health(health("gps", "degraded", **{**GOOD_GPS, **details}), 0.5)
    assert checks.evaluate(0.6, **OK) == [CheckFailure("gps", reason, "gps")]
    feed_good(checks, 0.9)
    assert checks.evaluate(1.0, **OK) == []


def test_gps_stale_data_fails_and_a_silent_gps_service_times_out(tmp_path: Path) -> None:
    checks = checks_for(tmp_path)
    feed_good(checks, 0.0)
    checks.on_health(health("gps", "degraded", **{**GOOD_GPS, "data": "stale", "last_data_age_s": "2.05"}), 1.0)
    feed_good(checks, 1.0, skip=("gps",))
    assert reasons(checks.evaluate(1.0, **OK)) == ["gps: no data from the receiver (stale)"]
    checks.on_health(health("gps", **GOOD_GPS), 1.5)
    feed_good(checks, 4.4, skip=("gps",))
    assert checks.evaluate(4.4, **OK) == []
    assert reasons(checks.evaluate(4.6, **OK)) == ["gps: no health for over 3 s"]


def test_a_degraded_gps_with_a_good_fix_fails_with_its_own_reason(tmp_path: Path) -> None:
    checks = checks_for(tmp_path)
    feed_good(checks, 0.0)
    checks.on_health(health("gps", "degraded", **GOOD_GPS, degraded_reason="port reconnecting"), 0.1)
    assert reasons(checks.evaluate(0.1, **OK)) == ["gps: degraded (port reconnecting)"]


def test_imu_not_calibrated_tells_the_pilot_to_keep_still_then_passes(tmp_path: Path) -> None:
    checks = checks_for(tmp_path)
    feed_good(checks, 0.0)
    checks.on_health(health("imu", "degraded", calibrated=False,
                            calibration="waiting for rest (moving: gyro std 2.10 deg/s > 0.5)"), 0.1)
    assert checks.evaluate(0.1, **OK) == [CheckFailure(
        "imu", "imu: not calibrated (waiting for rest (moving: gyro std 2.10 deg/s > 0.5); keep the vehicle still)",
        "imu")]
    checks.on_health(health("imu", "degraded", calibration="sys 0 gyr 3 acc 1 mag 0"), 0.2)
    assert reasons(checks.evaluate(0.2, **OK)) == [
        "imu: not calibrated (sys 0 gyr 3 acc 1 mag 0; turn the vehicle slowly through a figure eight)"]
    checks.on_health(health("imu", calibrated=True, calibration="calibrated"), 0.3)
    assert checks.evaluate(0.3, **OK) == []


def test_every_imu_is_judged_and_named(tmp_path: Path) -> None:
    services = {**SERVICES, "imu2": {"kind": "imu_bno055"}}
    checks = checks_for(tmp_path, services=services)
    assert checks.table.imu is not None and checks.table.imu.services == ("imu", "imu2")
    feed_good(checks, 0.0, skip=("imu2",))
    checks.on_health(health("imu2", calibrated=0, calibration="sys 1 gyr 3 acc 3 mag 0"), 0.0)
    assert reasons(checks.evaluate(0.1, **OK)) == [
        "imu imu2: not calibrated (sys 1 gyr 3 acc 3 mag 0; turn the vehicle slowly through a figure eight)"]


@pytest.mark.parametrize("msg, reason", [
    (estimate(x_sigma=8.7, y_sigma=8.7), "estimator: not converged (position sigma 12.3 m > 5 m)"),
    (estimate(psi_sigma=math.radians(20)), "estimator: not converged (heading sigma 20.0 deg > 10 deg)"),
    (estimate(position=False), "estimator: not converged (no position yet)"),
    (estimate(heading=False), "estimator: not converged (no heading yet)"),
    (estimate(y_sigma=None), "estimator: not converged (position sigma unknown > 5 m)"),
])
def test_estimator_not_converged_names_the_sigma_and_recovers(tmp_path: Path, msg: t.StateInformation,
                                                              reason: str) -> None:
    checks = checks_for(tmp_path)
    feed_good(checks, 0.0)
    checks.on_estimate(msg, 0.1)
    assert checks.evaluate(0.1, **OK) == [CheckFailure("estimator", reason, "estimator")]
    checks.on_estimate(estimate(), 0.2)
    assert checks.evaluate(0.2, **OK) == []


def test_a_frozen_estimator_fails_on_its_estimate_age_before_its_health_times_out(tmp_path: Path) -> None:
    checks = checks_for(tmp_path)
    feed_good(checks, 0.0)
    assert checks.evaluate(0.5, **OK) == []
    assert reasons(checks.evaluate(0.6, **OK)) == ["estimator: no STATE_ESTIMATE for over 0.5 s"]
    checks.on_estimate(estimate(source="other_estimator"), 0.7)          # another source is no evidence
    assert reasons(checks.evaluate(0.7, **OK)) == ["estimator: no STATE_ESTIMATE for over 0.5 s"]


def test_without_estimate_wiring_the_estimator_is_judged_from_its_health_details(tmp_path: Path) -> None:
    checks = checks_for(tmp_path, {"estimator": {"max_estimate_age_s": 0}})
    assert not checks.needs_estimate
    feed_good(checks, 0.0, skip=("estimator",))
    checks.on_health(health("estimator", position_sigma_m="6.5", heading_sigma_deg="1.0"), 0.0)
    assert reasons(checks.evaluate(0.1, **OK)) == ["estimator: not converged (position sigma 6.5 m > 5 m)"]
    checks.on_health(health("estimator", position_sigma_m="", heading_sigma_deg=""), 0.2)
    assert reasons(checks.evaluate(0.2, **OK)) == ["estimator: not converged (no position yet)"]
    checks.on_health(health("estimator", position_sigma_m="1.5", heading_sigma_deg="unknown"), 0.25)
    assert reasons(checks.evaluate(0.25, **OK)) == ["estimator: not converged (heading sigma unknown > 10 deg)"]
    checks.on_health(health("estimator", position_sigma_m="1.5", heading_sigma_deg="2.0"), 0.3)
    assert checks.evaluate(0.3, **OK) == []


def test_estimator_degraded_names_its_silent_sensors(tmp_path: Path) -> None:
    checks = checks_for(tmp_path)
    feed_good(checks, 0.0)
    checks.on_health(health("estimator", "degraded", silent_sensors="compass"), 0.1)
    assert reasons(checks.evaluate(0.1, **OK)) == ["estimator: degraded (silent sensors: compass)"]


@pytest.mark.parametrize("status, last_error, reason", [
    ("failed", "mission file unreadable", "required service world: failed (mission file unreadable)"),
    ("stopping", "", "required service world: stopped"),
    ("starting", "", "required service world: starting"),
    ("degraded", "a-priori objects not loaded", "required service world: degraded (a-priori objects not loaded)"),
])
def test_required_service_status_names_the_service(tmp_path: Path, status: str, last_error: str,
                                                   reason: str) -> None:
    checks = checks_for(tmp_path)
    feed_good(checks, 0.0)
    checks.on_health(health("world", status, last_error=last_error), 0.1)
    assert checks.evaluate(0.1, **OK) == [CheckFailure("required_services", reason, "world")]


def test_a_required_service_goes_stale_and_recovers(tmp_path: Path) -> None:
    checks = checks_for(tmp_path)
    feed_good(checks, 0.0)
    feed_good(checks, 3.3, skip=("world",))
    assert checks.evaluate(3.0, **OK) == []
    assert reasons(checks.evaluate(3.4, **OK)) == ["required service world: no health for over 3 s"]
    feed_good(checks, 5.0, skip=("world",))
    # a lasting failure reads the same at every evaluation: the host logs and publishes only changes
    assert reasons(checks.evaluate(5.0, **OK)) == ["required service world: no health for over 3 s"]
    checks.on_health(health("world"), 5.1)
    assert checks.evaluate(5.1, **OK) == []


def test_allow_degraded_and_ignore(tmp_path: Path) -> None:
    checks = checks_for(tmp_path, {"required_services": {"allow_degraded": ["planner"], "ignore": ["world"]}})
    assert "world" not in checks.watched
    feed_good(checks, 0.0)
    checks.on_health(health("planner", "degraded", doing="blocked: tree"), 0.1)
    assert checks.evaluate(0.1, **OK) == []
    checks.on_health(health("planner", "failed"), 0.2)
    assert reasons(checks.evaluate(0.2, **OK)) == ["required service planner: failed (no reason given)"]


def test_health_from_services_no_check_names_is_ignored(tmp_path: Path) -> None:
    checks = checks_for(tmp_path)
    assert "pan" not in checks.watched and "rc" not in checks.watched and "recorder" not in checks.watched
    feed_good(checks, 0.0)
    checks.on_health(health("pan", "failed"), 0.1)
    checks.on_health(health("rc", "degraded"), 0.1)
    assert checks.evaluate(0.1, **OK) == []


def test_a_kept_verdict_is_always_the_one_a_fresh_judgement_gives(tmp_path: Path) -> None:
    """evaluate() keeps its verdict between edges; at every step it must equal a judgement made afresh, at
    the age limits (a Health just past health_timeout_s, an estimate just past its age) included."""
    import random

    checks = checks_for(tmp_path, {"estimator": {"max_estimate_age_s": 0.5}, "health_timeout_s": 1.0})
    rnd = random.Random(7)
    now, kept, fresh_calls = 100.0, 0, 0
    for _ in range(4000):
        roll = rnd.random()
        if roll < 0.03:
            feed_good(checks, now, skip=tuple(n for n in checks.watched if rnd.random() < 0.3))
        elif roll < 0.05:
            checks.on_health(health("gps", **{**GOOD_GPS, "fix_type": rnd.choice(["3D", "2D"])}), now)
        elif roll < 0.07:
            checks.on_estimate(estimate(x_sigma=rnd.choice([0.5, 9.0])), now)
        link, failsafe = rnd.random() > 0.02, "hsm: test" if rnd.random() < 0.02 else ""
        before = checks._memo
        got = checks.evaluate(now, rc_link_ok=link, failsafe_reason=failsafe)
        kept += checks._memo is before
        fresh_calls += 1
        assert got == checks._judge_all(now, rc_link_ok=link, failsafe_reason=failsafe), now
        # steps that land on and around the limits: exactly 1.0 s / 0.5 s after an input, and 1 us either side
        now += rnd.choice([0.0, 0.001, 0.02, 0.25, 0.5, 1.0, 1e-6, 0.4999995, 0.9999995])
    assert 0 < kept < fresh_calls   # both paths ran


def test_describe_lists_what_runs(tmp_path: Path) -> None:
    text = checks_for(tmp_path).describe()
    assert text == ("pre-arm checks: no_failsafe; rc_link; gps (gps: 3D fix, sigma <= 5 m); imu (imu: calibrated); "
                    "estimator (estimator: sigma <= 5 m, <= 10 deg); required_services (world, planner)")


def test_an_hsm_degraded_by_another_service_does_not_take_autonomy_away() -> None:
    profile = load_profile(Path(__file__).parents[1] / "examples/ground_vehicle/vehicle.toml")
    table = PrearmChecks.from_profile(profile).table
    assert "hsm" in table.required_services.services and "hsm" in table.required_services.allow_degraded
    assert "control" not in table.required_services.allow_degraded
