"""Micro-benchmark: the State Estimator's CPU per State Information message (issue 27, part 1).

The example rover's estimator handles about 115 STATE_INFO messages a second in a mission:
IMU body rates (50 Hz), wheel odometry (~50 Hz), compass heading (10 Hz) and GPS position
with ground velocity (5 Hz), each composed as its driver composes it (``drivers/imu/common.py``,
``drivers/can_motor/common.py``, ``drivers/compass/driver.py``, ``drivers/gps_nmea/fix.py``), and publishes
STATE_ESTIMATE after each GPS and compass update and at least at ``publish_rate_hz`` (20 Hz).
This bench feeds the real service (its callback and its run loop's publication, on a
simulated clock, with a transport that only keeps what is published) a deterministic
sequence of such messages from a rover driving arcs, with a GPS outlier now and then so
that the gate and the re-initialisation work too, and prints the CPU (``time.process_time``)
per message by sensor and in all: the median of ``--runs`` runs of ``--seconds`` of driving.

``--dump FILE`` writes every published estimate (field values) as JSON, ``--compare FILE``
checks the estimates of this code against such a dump (1e-9 relative), so that an
optimisation can be shown not to change results. ``--profile`` prints cProfile's top
functions for one run instead.

    .venv/bin/python bench/estimator.py [--seconds 30] [--runs 5] [--dump F | --compare F] [--profile]
"""

from __future__ import annotations

import argparse
import json
import math
import random
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from u2sa_hw import channels as ch  # noqa: E402
from u2sa_hw import geo  # noqa: E402
from u2sa_hw import lcmtypes as t  # noqa: E402
from u2sa_hw import messages as m  # noqa: E402
from u2sa_hw.messages import STATE_FIELDS  # noqa: E402
from u2sa_hw.services.estimator.service import StateEstimator  # noqa: E402
from u2sa_hw.profile.loader import load_profile  # noqa: E402

PROFILE = Path(__file__).resolve().parent.parent / "examples" / "ground_vehicle" / "vehicle.toml"
# sensor -> (period s, phase s): the live rates, phases apart as independent drivers are
RATES = {"imu": (0.02, 0.003), "wheels": (0.02, 0.013), "compass": (0.1, 0.041), "gps": (0.2, 0.077)}
OUTLIER_EVERY_S = 10.0   # a GPS fix 70 m off, then and then (gated, counted as an outlier)

Schedule = list[tuple[float, str, t.StateInformation]]


class KeepingTransport:
    """Stands in for the bus: subscriptions are accepted and dropped, publications kept."""

    def __init__(self) -> None:
        self.published: list[t.StateInformation] = []

    def subscribe(self, channel: str, msg_type: type, handler: Callable[..., None]) -> object:
        return (channel, handler)

    def unsubscribe(self, sub: object) -> None:
        pass

    def publish(self, channel: str, msg: Any) -> bool:
        if channel == ch.STATE_ESTIMATE:
            self.published.append(msg)
        return True

    def __getattr__(self, name: str) -> Any:   # anything else the service may touch: a no-op
        return lambda *args, **kwargs: None


def _state(sensor: str, frame: str, stamp: float, **fields: float) -> t.StateInformation:
    msg = m.StateInformation().set(**fields)
    msg.sensor_name, msg.reference_frame = sensor, frame
    msg.header.timestamp_us = int(stamp * 1e6)
    return msg


def schedule(*, seconds: float, seed: int = 3) -> Schedule:
    """The messages of *seconds* of driving in arcs at the live rates, in time order."""
    rng = random.Random(seed)
    events = sorted((k * period + phase, sensor) for sensor, (period, phase) in RATES.items()
                    for k in range(int(seconds / period)))
    north = east = 0.0
    yaw, now = 2.8, 0.0
    out: Schedule = []
    for at, sensor in events:
        speed = 1.2
        yaw_rate = 0.25 if int(at // 8) % 2 == 0 else -0.1
        dt, now = at - now, at
        north += speed * math.cos(yaw) * dt
        east += speed * math.sin(yaw) * dt
        yaw = geo.wrap_angle(yaw + yaw_rate * dt)
        if sensor == "imu":
            rates = (rng.gauss(0, 0.01), rng.gauss(0, 0.01), yaw_rate + rng.gauss(0, 0.01))
            accel = (rng.gauss(0, 0.3), speed * yaw_rate + rng.gauss(0, 0.3), rng.gauss(0, 0.3))
            msg = _state("imu", "FRD", at, phi_dot=rates[0], theta_dot=rates[1], psi_dot=rates[2],
                         phi_dot_sigma=0.01, theta_dot_sigma=0.01, psi_dot_sigma=0.01,
                         x_ddot=accel[0], y_ddot=accel[1], z_ddot=accel[2],
                         x_ddot_sigma=0.3, y_ddot_sigma=0.3, z_ddot_sigma=0.3)
        elif sensor == "wheels":
            msg = _state("wheels", "FRD", at, x_dot=speed + rng.gauss(0, 0.05), y_dot=0.0,
                         psi_dot=yaw_rate + rng.gauss(0, 0.05), x_dot_sigma=0.05, y_dot_sigma=0.05,
                         psi_dot_sigma=0.05)
        elif sensor == "compass":
            msg = _state("compass", "NED", at, psi=geo.wrap_angle(yaw + rng.gauss(0, 0.017)),
                         psi_sigma=math.radians(1.0))
        else:
            jump = 70.0 if at % OUTLIER_EVERY_S < RATES["gps"][0] and at > 5.0 else 0.0
            msg = _state("gps", "NED", at, x=north + rng.gauss(0, 0.5) + jump, y=east + rng.gauss(0, 0.5),
                         z=-rng.gauss(0, 1.0), x_sigma=0.5, y_sigma=0.5, z_sigma=1.2,
                         x_dot=speed * math.cos(yaw) + rng.gauss(0, 0.1),
                         y_dot=speed * math.sin(yaw) + rng.gauss(0, 0.1), x_dot_sigma=0.1, y_dot_sigma=0.1)
        out.append((at, sensor, msg))
    return out


class SimClock:
    """The service's clock, set by the bench."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def new_estimator() -> tuple[StateEstimator, KeepingTransport, SimClock]:
    """The example rover's estimator with its own config, on a simulated clock."""
    profile = load_profile(PROFILE)
    spec = profile.services["estimator"]
    transport = KeepingTransport()
    svc = StateEstimator("estimator", profile=profile, config_path=spec.config_path, settings=spec.settings,
                         transport=transport)  # type: ignore[arg-type]
    clock = SimClock()
    svc.clock = clock  # type: ignore[method-assign]
    return svc, transport, clock


def run_once(messages: Schedule, *, per_kind: dict[str, list[float]] | None = None
             ) -> tuple[float, list[t.StateInformation]]:
    """Feed *messages* to a fresh estimator; CPU seconds in all, and what it published.

    With *per_kind*, each callback is timed on its own and its CPU appended under its sensor
    (the run loop's publications under ``rate``).
    """
    svc, transport, clock = new_estimator()
    period = 1.0 / float(svc.config.get("publish_rate_hz"))
    due = messages[0][0] + period
    cpu = time.process_time
    start = cpu()
    for at, sensor, msg in messages:
        while due <= at:   # the run loop wakes at its due time and publishes if nothing went out
            clock.now = due
            if per_kind is None:
                nxt = svc.publish_if_due(due)
            else:
                t0 = cpu()
                nxt = svc.publish_if_due(due)
                per_kind["rate"].append(cpu() - t0)
            # a due time a rounding short of the period returns itself; the live loop's clock moves on
            due = nxt if nxt > due else due + 1e-9
        clock.now = at
        if per_kind is None:
            svc.callback(msg)
        else:
            t0 = cpu()
            svc.callback(msg)
            per_kind[sensor].append(cpu() - t0)
    return cpu() - start, transport.published


def estimates_as_rows(published: list[t.StateInformation]) -> list[list[float]]:
    """Each published estimate as its presence vector and present field values."""
    return [[msg.presence_vector, *(getattr(msg, n) for i, n in enumerate(STATE_FIELDS) if msg.presence_vector >> i & 1)]
            for msg in published]


def compare(rows: list[list[float]], reference: list[list[float]]) -> str:
    """"" when *rows* equal *reference* to 1e-9 relative (1e-12 absolute), else the first difference."""
    if len(rows) != len(reference):
        return f"{len(rows)} estimates published, the reference has {len(reference)}"
    for i, (row, ref) in enumerate(zip(rows, reference)):
        if len(row) != len(ref) or row[0] != ref[0]:
            return f"estimate {i}: fields differ (presence {row[0]:#x} vs {ref[0]:#x})"
        for a, b in zip(row[1:], ref[1:]):
            if not math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12):
                return f"estimate {i}: {a!r} vs {b!r}"
    return ""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=30.0, help="simulated driving per run")
    ap.add_argument("--runs", type=int, default=5, help="runs; the median is reported")
    ap.add_argument("--dump", type=Path, help="write the published estimates (JSON) here")
    ap.add_argument("--compare", type=Path, help="check the published estimates against this dump")
    ap.add_argument("--profile", action="store_true", help="cProfile one run and print the top functions")
    args = ap.parse_args()
    messages = schedule(seconds=args.seconds)
    run_once(messages[:200])   # imports, caches, first allocations
    if args.profile:
        import cProfile
        import pstats
        prof = cProfile.Profile()
        prof.runcall(run_once, messages)
        pstats.Stats(prof).sort_stats("tottime").print_stats(25)
        return 0
    totals: list[float] = []
    kinds: dict[str, list[float]] = {k: [] for k in (*RATES, "rate")}
    published: list[t.StateInformation] = []
    for _ in range(args.runs):
        total, published = run_once(messages)
        totals.append(total)
        per_kind: dict[str, list[float]] = {k: [] for k in kinds}
        run_once(messages, per_kind=per_kind)
        for k, values in per_kind.items():
            kinds[k].append(sum(values) / max(len(values), 1))
    n = len(messages)
    counts = {k: sum(1 for _, s, _ in messages if s == k) for k in RATES}
    print(f"{n} messages ({args.seconds:g} s: " + ", ".join(f"{k} {c}" for k, c in counts.items())
          + f"), {len(published)} estimates published; median of {args.runs} runs (process_time)")
    for k, values in kinds.items():
        print(f"  {k:8s} {statistics.median(values) * 1e6:7.1f} us per call")
    med = statistics.median(totals)
    print(f"  all      {med / n * 1e6:7.1f} us per message (publications included), "
          f"{med / args.seconds * 100:.2f} % of a core at these rates")
    rows = estimates_as_rows(published)
    if args.dump:
        args.dump.write_text(json.dumps(rows))
        print(f"estimates written to {args.dump}")
    if args.compare:
        problem = compare(rows, json.loads(args.compare.read_text()))
        print(f"estimates vs {args.compare}: {problem or 'same (1e-9 relative)'}")
        return 1 if problem else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
