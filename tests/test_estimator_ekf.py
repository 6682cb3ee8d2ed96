"""The State Estimator's EKF: convergence on simulated noisy sensors, gating, frames, and the service."""

from __future__ import annotations

import math
import random
from pathlib import Path

import numpy as np
import pytest
from conftest import ServiceProcesses, wait_until

from u2sa_hw.mocks.vehicle_sim import SimVehicle
from u2sa_hw import channels as ch
from u2sa_hw import geo
from u2sa_hw import lcmtypes as t
from u2sa_hw import messages as m
from u2sa_hw.bus.client import BusClient
from u2sa_hw.services.estimator.ekf import Measurement, NavigationEkf, chi2_quantile
from u2sa_hw.services.estimator.fusion import FusionSettings, StateFusion
from u2sa_hw.services.estimator.service import estimate_sigmas
from u2sa_hw.profile.vehicle import Origin

ORIGIN = Origin(lat=29.1895, lon=-81.0483, alt=10.0)


def info(sensor: str, frame: str = "NED", **fields: float) -> t.StateInformation:
    msg = m.StateInformation().set(**fields)
    msg.sensor_name, msg.reference_frame = sensor, frame
    return msg


def gps_fix(north: float, east: float, sigma: float = 2.0) -> t.StateInformation:
    lat, lon, _ = geo.ned_to_geodetic(north, east, 0.0, origin=ORIGIN)
    return info("gps", "GEODETIC", x=lat, y=lon, x_sigma=sigma, y_sigma=sigma)


def drive(fusion: StateFusion, *, seconds: float, seed: int = 7, gps_sigma: float = 2.0,
          outlier_at: float | None = None) -> dict[str, list[float]]:
    """Drive a simulated rover in arcs; feed noisy GPS (5 Hz), compass (10 Hz), odometry + gyro (20 Hz)."""
    rng = random.Random(seed)
    sim = SimVehicle(origin_lat=ORIGIN.lat, origin_lon=ORIGIN.lon, origin_alt=ORIGIN.alt, start_yaw=2.8)
    out: dict[str, list[float]] = {"pos": [], "raw": [], "psi": [], "speed": [], "jump": []}
    dt = 0.01
    for k in range(int(seconds / dt)):
        now = k * dt
        turning = int(now // 8) % 2 == 0
        sim.set_wheel_speed("left", 1.3 if turning else 1.0)
        sim.set_wheel_speed("right", 0.7 if turning else 1.0)
        sim.step(dt)
        truth = sim.snapshot()
        if k % 20 == 0:
            n, e = truth.north + rng.gauss(0, gps_sigma), truth.east + rng.gauss(0, gps_sigma)
            if outlier_at is not None and abs(now - outlier_at) < dt / 2:
                before = fusion.estimate()
                fusion.ingest(gps_fix(n + 60.0, e - 40.0, gps_sigma), now=now)
                after = fusion.estimate()
                out["jump"].append(math.hypot(after.x - before.x, after.y - before.y))
            else:
                fusion.ingest(gps_fix(n, e, gps_sigma), now=now)
            out["raw"].append(math.hypot(n - truth.north, e - truth.east))
        if k % 10 == 5:
            psi = geo.wrap_angle(truth.yaw + rng.gauss(0, 0.05))
            fusion.ingest(info("compass", psi=psi, psi_sigma=0.05), now=now)
        if k % 5 == 2:
            fusion.ingest(info("odometry", "FRD", x_dot=truth.speed + rng.gauss(0, 0.05), x_dot_sigma=0.05,
                               y_dot=rng.gauss(0, 0.05), y_dot_sigma=0.05,   # wheels do not slide sideways
                               psi_dot=truth.yaw_rate + rng.gauss(0, 0.01), psi_dot_sigma=0.01), now=now)
        if now > 10.0 and k % 10 == 0:
            fusion.predict_to(now)
            est = fusion.estimate()
            out["pos"].append(math.hypot(est.x - truth.north, est.y - truth.east))
            out["psi"].append(abs(geo.wrap_angle(est.psi - truth.yaw)))
            out["speed"].append(abs(math.hypot(est.x_dot, est.y_dot) - truth.speed))
    return out


def rms(values: list[float]) -> float:
    return math.sqrt(sum(v * v for v in values) / len(values))


def test_converges_on_noisy_gps_compass_and_odometry() -> None:
    fusion = StateFusion(origin=ORIGIN)
    errors = drive(fusion, seconds=60.0)
    assert rms(errors["pos"]) < 0.4 * rms(errors["raw"])     # much better than the raw 2 m GPS
    assert rms(errors["pos"]) < 1.2
    assert max(errors["psi"]) < math.radians(6) and rms(errors["speed"]) < 0.15
    assert {n: r.outliers for n, r in fusion.sensors.items()} == {"gps": 0, "compass": 0, "odometry": 0}
    est = fusion.estimate()
    assert est.reference_frame == "NED" and 0 < est.x_sigma < 2.0 and 0 < est.psi_sigma < 0.05
    assert not est.has("z")                                    # nobody measured altitude


def test_outlier_is_rejected_and_counted_per_sensor() -> None:
    fusion = StateFusion(origin=ORIGIN)
    errors = drive(fusion, seconds=30.0, outlier_at=20.0)
    assert fusion.sensors["gps"].outliers == 1 and fusion.sensors["compass"].outliers == 0
    assert errors["jump"] and errors["jump"][0] < 0.5          # a 72 m jump moved the estimate < 0.5 m
    assert max(errors["pos"]) < 3.0


def test_a_sensor_that_keeps_disagreeing_is_trusted_again_after_reinit_after() -> None:
    fusion = StateFusion(origin=ORIGIN, settings=FusionSettings(reinit_after=3))
    for i in range(20):
        fusion.ingest(info("gps", x=10.0, y=5.0, x_sigma=0.5, y_sigma=0.5), now=i * 0.1)
    for i in range(3):                                          # the sensor was moved 200 m
        fusion.ingest(info("gps", x=210.0, y=5.0, x_sigma=0.5, y_sigma=0.5), now=2.0 + i * 0.1)
    assert fusion.sensors["gps"].outliers == 3
    assert fusion.estimate().x == pytest.approx(210.0, abs=1.0)


def test_each_message_updates_only_its_present_fields_with_default_sigmas() -> None:
    fusion = StateFusion(origin=ORIGIN, settings=FusionSettings(default_position_sigma=4.0,
                                                                default_heading_sigma=0.2))
    fusion.ingest(info("a", x=7.0), now=0.0)
    est = fusion.estimate()
    assert est.x == 7.0 and est.x_sigma == pytest.approx(4.0) and not est.has("y") and not est.has("psi")
    fusion.ingest(info("b", psi=math.radians(90)), now=0.0)
    est = fusion.estimate()
    assert est.psi == pytest.approx(math.pi / 2) and est.psi_sigma == pytest.approx(0.2) and not est.has("y")
    fusion.ingest(info("a", x=7.0, x_sigma=float("nan"), y=float("inf")), now=0.1)   # NaN sigma -> default
    assert fusion.sensors["a"].unusable == 1 and not fusion.estimate().has("y")


def test_the_filter_computes_what_filterpy_computes() -> None:
    """filterpy's ExtendedKalmanFilter beside NavigationEkf on the same measurements: same state and covariance."""
    from filterpy.common import Q_continuous_white_noise
    from filterpy.kalman import ExtendedKalmanFilter

    noise = {(0, 3): 2.0, (1, 4): 2.0, (2, 5): 0.3, (6, 7): 4.0}
    ekf = NavigationEkf(accel_noise=2.0, vertical_accel_noise=0.3, yaw_accel_noise=4.0, gate_probability=1.0)
    ekf.predict_to(0.0)
    ekf.update(Measurement("position", ("north", "east", "down"), (3.0, -4.0, 1.0), (1.0, 1.0, 2.0)))
    ekf.update(Measurement("heading", ("psi",), (3.1,), (0.05,)))
    ref = ExtendedKalmanFilter(dim_x=8, dim_z=1)
    ref.x, ref.P = ekf.x.reshape(8, 1).copy(), ekf.P.copy()

    def model(m: Measurement) -> tuple[np.ndarray, np.ndarray]:
        """h(x) and H at the reference's state, written from the model in ekf.py's docstring."""
        x = ref.x[:, 0]
        index = {"north": 0, "east": 1, "down": 2, "v_north": 3, "v_east": 4, "v_down": 5, "psi": 6, "yaw_rate": 7}
        c, s_ = math.cos(x[6]), math.sin(x[6])
        h, jac = np.zeros((len(m.components), 1)), np.zeros((len(m.components), 8))
        for row, comp in enumerate(m.components):
            if m.kind == "velocity_body" and comp == "forward":
                h[row, 0], jac[row, [3, 4, 6]] = x[3] * c + x[4] * s_, (c, s_, -x[3] * s_ + x[4] * c)
            elif m.kind == "velocity_body" and comp == "right":
                h[row, 0], jac[row, [3, 4, 6]] = -x[3] * s_ + x[4] * c, (-s_, c, -x[3] * c - x[4] * s_)
            else:
                i = 5 if m.kind == "velocity_body" else index[comp]
                h[row, 0], jac[row, i] = x[i], 1.0
        return h, jac

    def residual(z: np.ndarray, hx: np.ndarray, psi_rows: list[int]) -> np.ndarray:
        y = z - hx
        for i in psi_rows:
            y[i, 0] = geo.wrap_angle(y[i, 0])
        return y

    kinds = [("position", ("north", "east")), ("position", ("north", "east", "down")), ("heading", ("psi",)),
             ("velocity_ned", ("v_north", "v_east")), ("velocity_body", ("forward", "right")),
             ("velocity_body", ("forward", "right", "down")), ("yaw_rate", ("yaw_rate",))]
    rng = random.Random(5)
    now = 0.0
    for step in range(400):
        dt = rng.choice((0.004, 0.02, 0.1, 0.35))
        now += dt
        ekf.predict_to(now)
        ref.F, ref.Q = np.eye(8), np.zeros((8, 8))
        for (pos, vel), density in noise.items():
            ref.F[pos, vel] = dt
            ref.Q[np.ix_([pos, vel], [pos, vel])] = Q_continuous_white_noise(dim=2, dt=dt, spectral_density=density ** 2)
        ref.predict()
        ref.x[6, 0] = geo.wrap_angle(ref.x[6, 0])
        kind, comps = rng.choice(kinds)
        values = tuple(rng.uniform(-3.2, 3.2) if c == "psi" else rng.gauss(0.0, 3.0) for c in comps)
        m = Measurement(kind, comps, values, tuple(rng.uniform(0.05, 2.0) for _ in comps))
        assert ekf.update(m).outcome == "accepted"
        h, jac = model(m)
        psi_rows = [i for i, c in enumerate(comps) if c == "psi"]
        ref.update(np.array(values).reshape(-1, 1), HJacobian=lambda _x: jac, Hx=lambda _x: h,
                   R=np.diag(np.square(m.sigmas)), residual=lambda z, hx: residual(z, hx, psi_rows))
        ref.x[6, 0] = geo.wrap_angle(ref.x[6, 0])
        assert ekf.x == pytest.approx(ref.x[:, 0], rel=1e-9, abs=1e-9), f"state after step {step} ({kind})"
        assert ekf.P == pytest.approx(ref.P, rel=1e-9, abs=1e-9), f"covariance after step {step} ({kind})"


def test_gate_quantiles_are_scipys() -> None:
    from scipy.stats import chi2

    for dof in range(1, 7):
        for p in (0.5, 0.9, 0.99, 0.999, 0.999999):
            assert chi2_quantile(p, dof) == pytest.approx(chi2.ppf(p, dof), rel=1e-9)
    assert NavigationEkf(gate_probability=1.0).gate_threshold(2) == math.inf
    with pytest.raises(ValueError):
        chi2_quantile(1.0, 2)


def test_heading_innovation_is_wrapped_across_pi() -> None:
    ekf = NavigationEkf()
    ekf.update(Measurement("heading", ("psi",), (math.pi - 0.02,), (0.05,)))
    result = ekf.update(Measurement("heading", ("psi",), (-math.pi + 0.02,), (0.05,)))
    assert result.outcome == "accepted" and result.mahalanobis2 < 1.0   # 0.04 rad apart, not 6.24
    psi = ekf.state()["psi"][0]
    assert abs(geo.wrap_angle(psi - math.pi)) < 0.01 and -math.pi <= psi < math.pi


def test_body_frame_speed_moves_the_position_along_the_heading() -> None:
    fusion = StateFusion(origin=ORIGIN)
    fusion.ingest(info("gps", x=0.0, y=0.0, x_sigma=0.1, y_sigma=0.1), now=0.0)
    fusion.ingest(info("compass", psi=math.radians(90), psi_sigma=0.01), now=0.0)   # facing east
    for i in range(1, 51):
        fusion.ingest(info("wheels", "FRD", x_dot=2.0, x_dot_sigma=0.02), now=i * 0.1)
    est = fusion.estimate()
    assert est.y_dot == pytest.approx(2.0, abs=0.05) and abs(est.x_dot) < 0.05
    assert est.y == pytest.approx(10.0, abs=1.0) and abs(est.x) < 0.5
    fusion.ingest(info("wheels", "FRD", x=5.0), now=5.1)           # a position in the body frame: unusable
    assert fusion.sensors["wheels"].unusable == 1


def test_geodetic_position_and_altitude_use_the_profile_origin() -> None:
    fusion = StateFusion(origin=ORIGIN)
    lat, lon, alt = geo.ned_to_geodetic(-30.0, 12.0, -4.0, origin=ORIGIN)
    fusion.ingest(info("gps", "GEODETIC", x=lat, y=lon, z=alt), now=0.0)
    est = fusion.estimate()
    assert (est.x, est.y, est.z) == pytest.approx((-30.0, 12.0, -4.0), abs=1e-6)
    fusion.ingest(info("gps", "GEODETIC", x=lat), now=0.1)         # latitude alone: unusable
    assert fusion.sensors["gps"].unusable == 1


def test_geo_round_trip_and_scale() -> None:
    north, east, down = geo.geodetic_to_ned(ORIGIN.lat + 0.001, ORIGIN.lon + 0.001, 20.0, origin=ORIGIN)
    assert north == pytest.approx(110.8, abs=0.3) and east == pytest.approx(97.3, abs=0.3) and down == -10.0
    assert geo.ned_to_geodetic(north, east, down, origin=ORIGIN) == pytest.approx(
        (ORIGIN.lat + 0.001, ORIGIN.lon + 0.001, 20.0), abs=1e-9)
    near_antimeridian = Origin(lat=0.0, lon=179.9999)
    assert geo.geodetic_to_ned(0.0, -179.9999, origin=near_antimeridian)[1] == pytest.approx(22.3, abs=0.1)
    assert geo.wrap_angle(3 * math.pi) == pytest.approx(-math.pi)
    assert geo.body_to_ned(1.0, 0.0, math.pi / 2) == pytest.approx((0.0, 1.0))
    assert geo.ned_to_body(*geo.body_to_ned(0.3, -0.7, 1.1), 1.1) == pytest.approx((0.3, -0.7))


def _details(h: t.Health) -> dict[str, str]:
    return {kv.key: kv.value for kv in h.details}


def test_estimate_sigmas_are_horizontal_and_in_degrees_empty_until_estimated() -> None:
    assert estimate_sigmas(None) == {"position_sigma_m": "", "heading_sigma_deg": ""}
    assert estimate_sigmas(info("est", x=1.0, y=2.0, x_sigma=3.0, y_sigma=4.0, psi=0.1,
                                psi_sigma=math.radians(2.5))) == {"position_sigma_m": "5.00",
                                                                  "heading_sigma_deg": "2.50"}
    assert estimate_sigmas(info("est", x=1.0, y=2.0, psi=0.1)) == {"position_sigma_m": "unknown",
                                                                   "heading_sigma_deg": "unknown"}
    assert estimate_sigmas(info("est", x=1.0, x_sigma=1.0)) == {"position_sigma_m": "", "heading_sigma_deg": ""}


def test_service_fuses_gps_publishes_at_its_rate_and_reports_outliers_and_silence(
        services: ServiceProcesses, bus: BusClient, tmp_path: Path) -> None:
    vehicle = tmp_path / "vehicle.toml"
    vehicle.write_text(f"[vehicle]\norigin = {{ lat = {ORIGIN.lat}, lon = {ORIGIN.lon}, alt = {ORIGIN.alt} }}\n"
                       "[services.est]\nkind = \"state_estimator\"\n"
                       "settings = { sensor_timeout_s = 0.5, health_interval_s = 0.2 }\n")
    estimates: list[t.StateInformation] = []
    health: list[t.Health] = []
    bus.transport.subscribe(ch.STATE_ESTIMATE, t.StateInformation, lambda _c, msg: estimates.append(msg))
    bus.transport.subscribe(ch.HEALTH, t.Health, lambda _c, msg: health.append(msg) if msg.name == "est" else None)
    services.start("est", "--vehicle", str(vehicle))
    wait_until(lambda: health, timeout=20, message="the estimator's health")
    assert not estimates                                       # nothing to estimate yet

    def fix_seen(north: float) -> bool:
        bus.publish(ch.STATE_INFO, gps_fix(north, -8.0, sigma=1.0))
        return any(e.has("x") and abs(e.x - north) < 0.5 for e in estimates[-5:])

    wait_until(lambda: fix_seen(25.0), timeout=10, message="an estimate at the GPS fix")
    est = estimates[-1]
    assert est.y == pytest.approx(-8.0, abs=0.5) and 0 < est.x_sigma < 1.5 and est.reference_frame == "NED"
    count = len(estimates)
    wait_until(lambda: len(estimates) >= count + 10, timeout=5, message="estimates at the publish rate, unprompted")

    bus.publish(ch.STATE_INFO, gps_fix(525.0, -8.0, sigma=1.0))          # 500 m off: an outlier
    wait_until(lambda: _details(health[-1]).get("outliers") == "gps:1", timeout=10, message="gps:1 outliers")
    assert abs(estimates[-1].x - 25.0) < 1.0
    wait_until(lambda: _details(health[-1]).get("silent_sensors") == "gps" and health[-1].status == "degraded",
               timeout=10, message="the silent GPS in health")


def test_service_publishes_each_position_fix_at_once_with_the_rate_as_the_longest_silence(
        services: ServiceProcesses, bus: BusClient, tmp_path: Path) -> None:
    vehicle = tmp_path / "vehicle.toml"
    # one prediction per 30 s at most: the estimates that answer the fixes below can only be update publications
    vehicle.write_text(f"[vehicle]\norigin = {{ lat = {ORIGIN.lat}, lon = {ORIGIN.lon}, alt = {ORIGIN.alt} }}\n"
                       "[services.est]\nkind = \"state_estimator\"\n"
                       "settings = { publish_rate_hz = 0.033, publish_on = \"position\", health_interval_s = 0.2 }\n")
    estimates: list[t.StateInformation] = []
    health: list[t.Health] = []
    bus.transport.subscribe(ch.STATE_ESTIMATE, t.StateInformation, lambda _c, msg: estimates.append(msg))
    bus.transport.subscribe(ch.HEALTH, t.Health, lambda _c, msg: health.append(msg) if msg.name == "est" else None)
    services.start("est", "--vehicle", str(vehicle))
    wait_until(lambda: health, timeout=20, message="the estimator's health")
    assert (_details(health[0])["position_sigma_m"], _details(health[0])["heading_sigma_deg"]) == ("", "")
    bus.publish(ch.STATE_INFO, info("compass", psi=0.5, psi_sigma=0.05))     # a heading: not in publish_on
    wait_until(lambda: _details(health[-1]).get("sensors") == "compass", timeout=10, message="the compass registered")
    for k, north in enumerate((5.0, 5.3, 5.6)):
        bus.publish(ch.STATE_INFO, gps_fix(north, 2.0, sigma=1.0))
        wait_until(lambda: len(estimates) > k, timeout=10, message=f"the estimate answering fix {k + 1}")
    est = estimates[-1]
    assert 5.0 < est.x < 5.6 and est.y == pytest.approx(2.0, abs=0.5)
    assert est.psi == pytest.approx(0.5, abs=0.01)                              # the heading was folded in
    wait_until(lambda: int(_details(health[-1]).get("published_on_update", 0)) >= 3, timeout=10,
               message="three publications on update in health")
    # the pre-arm estimator check's fallback evidence: horizontal and heading sigmas of the estimate
    details = _details(health[-1])
    assert 0 < float(details["position_sigma_m"]) < 2.0 and 0 < float(details["heading_sigma_deg"]) < 90.0
    # a rate that is not > 0 is refused over the bus, and the file keeps the old one
    reply = bus.set_config("est", "publish_rate_hz", "0", timeout=10)
    assert reply is not None and not reply.ok and "field 'publish_rate_hz' must be > 0 and <= 1000; got 0.0" in reply.error
    reply = bus.set_config("est", "publish_on", "position,altitude", timeout=10)
    assert reply is not None and not reply.ok and "'publish_on' names altitude" in reply.error


def test_passthrough_mode_stays_selectable_and_a_bad_mode_is_one_clear_error(
        services: ServiceProcesses, bus: BusClient, tmp_path: Path) -> None:
    vehicle = tmp_path / "vehicle.toml"
    vehicle.write_text('[services.est]\nkind = "state_estimator"\nsettings = { mode = "passthrough" }\n'
                       '[services.bad]\nkind = "state_estimator"\nsettings = { mode = "kalman" }\n')
    bad = services.cli("service", "bad", "--vehicle", str(vehicle))
    assert bad.returncode != 0 and """field 'mode' must be one of "ekf", "passthrough"; got "kalman\"""" in bad.stderr
    estimates: list[t.StateInformation] = []
    bus.transport.subscribe(ch.STATE_ESTIMATE, t.StateInformation, lambda _c, msg: estimates.append(msg))
    services.start("est", "--vehicle", str(vehicle))

    def copied() -> bool:
        bus.publish(ch.STATE_INFO, info("gps", x=3.0, psi=1.25))
        return bool(estimates)

    wait_until(copied, timeout=20, message="a pass-through estimate")
    assert estimates[-1].present_fields() == ["x", "psi"] and (estimates[-1].x, estimates[-1].psi) == (3.0, 1.25)
