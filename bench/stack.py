#!/usr/bin/env python3
"""The whole stack on simulated hardware: sensor-to-actuator latency, CPU and memory, message rates.

Two runs of the example ground vehicle (``u2sa sim`` as a library, each on a bus and CAN
port of its own):

1. **Mission.** The example mission, as ``make sim`` drives it. While the vehicle drives
   (from the pilot's switch to the mission's end): the CPU % (of one core) and the largest
   RSS and PSS (``/proc/PID/smaps_rollup``) of every service process, from psutil on the
   launcher's children (CPU = user + system time used during the window / the window), each
   service's CPU split into its own loop, its bus handler and its health publisher (the
   threads a service names), their totals against the aims (10 % of one core, 200 MB PSS),
   the same for the ``u2sa sim`` process that hosts the mocks and the simulator, and the rate
   of every channel on the bus (bench/stack_meter.py). ``--no-realtime``: the safety chain
   and the sim at normal priority.
2. **Latency.** From an NMEA sentence written to the GPS pty to the CAN frame it causes.
   The rover is held still (wheels in the air: motor commands arrive, nothing moves),
   sensor noise is off and the control system's integrators are off, so the motor
   commands change only when an input does. Then the GPS mock's position jumps 4 m east
   and back at every epoch (5 Hz), so every epoch carries a large innovation for the
   estimator. For every GPS epoch: t0 = when the mock wrote its first sentence (GGA) to the
   pty (the mock's history); then the causal chain, each stage's first output after its
   input: the GPS driver's STATE_INFO, the next STATE_ESTIMATE, the first NAV_POINT and
   ACTUATOR_CMD that changed (receive times on this process's bus listener), and when the
   mock ODrives received the Set_Input_Vel frame carrying that command (matched by value:
   the listener hears a command a little after the driver does). That frame's time - t0
   is the latency.

   A black-box check follows: the first frame that moved by more than ``--threshold``
   rev/s after t0. It includes the controller's own dynamics (a heading PID's derivative,
   the speed loop on the predicted velocity): an epoch whose first command moved a wheel
   by less than the threshold is counted at the next control cycle, 50 ms later.

Usage: ``python bench/stack.py [--vehicle PATH] [--latency-s 30] [--skip-mission]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import statistics
import sys
import tempfile
import threading
import time
import tomllib
from collections import defaultdict
from pathlib import Path
from typing import Any

import psutil
import tomli_w

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from u2sa_hw.bus.run_keys import use_run_key  # noqa: E402
from u2sa_hw import channels as ch  # noqa: E402
from u2sa_hw import lcmtypes as t  # noqa: E402
from u2sa_hw.protocols import odrive_cansimple as cs  # noqa: E402
from u2sa_hw.simulation.progress import ProgressLine  # noqa: E402
from u2sa_hw.simulation.runner import SimOptions, SimRun  # noqa: E402
from u2sa_hw.bus.transport import Transport  # noqa: E402
from stack_meter import CPU_AIM_PCT, PSS_AIM_MB, RateCounter, ResourceMeter  # noqa: E402
from u2sa_hw.bus.udp_ports import private_udp_port  # noqa: E402

LATENCY_MISSION = """<?xml version="1.0"?>
<mission name="straight ahead" loop="false">
  <waypoint><name>ahead</name><x>15</x><y>0</y><threshold>1.0</threshold></waypoint>
</mission>
"""


STEP_M = 4.0   # the GPS position step, east (m); well inside the estimator's outlier gate


def options(vehicle: Path, out: Path, *, realtime: bool) -> SimOptions:
    port = private_udp_port()
    return SimOptions(vehicle=vehicle, out=out, lcm_url=f"udpm://239.255.76.67:{port}?ttl=0",
                      can_port=private_udp_port(), timeout_s=600, realtime=realtime)


def pct(values: list[float], q: float) -> float:
    """The q-quantile (0..1) of *values*, nearest rank."""
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, round(q * (len(ordered) - 1))))]


# -- phase 1: resources and rates ---------------------------------------------------------
def mission_phase(vehicle: Path, out: Path, *, realtime: bool) -> None:
    run = SimRun(options(vehicle, out / "mission", realtime=realtime), progress=ProgressLine(interactive=False, plain_every_s=30))
    try:
        run.start()
        run.wait_ready()
        run.engage()
        pids = {s.name: s.pid for s in run.launcher.status() if s.pid}
        meter, rates = ResourceMeter(pids), RateCounter(run.monitor.transport.url)
        run.drive()
        usage, (window, counts) = meter.stop(), rates.stop()
    finally:
        summary = run.finish()
    print(f"\n== mission: {summary['result']} in {summary['mission_time_s']} s; measured over {window:.1f} s of driving")
    kinds = ("loop", "bus", "health", "other")
    print(f"{'process':30} {'CPU % of 1 core':>16} {'(loop':>6} {'bus':>5} {'health':>6} {'other)':>6} "
          f"{'RSS MB':>8} {'PSS MB':>8}")
    services = {n: v for n, v in usage.items() if not n.startswith("(")}
    split_total: dict[str, float] = defaultdict(float)
    for name, (cpu, rss, pss) in sorted(services.items(), key=lambda kv: -kv[1][0]):
        split = meter.threads.get(name, {})
        for k in kinds:
            split_total[k] += split.get(k, 0.0)
        print(f"{name:30} {cpu:16.1f} " + " ".join(f"{split.get(k, 0.0):{w}.1f}" for k, w in zip(kinds, (6, 5, 6, 6)))
              + f" {rss:8.1f} {pss:8.1f}")
    total_cpu, total_pss = sum(v[0] for v in services.values()), sum(v[2] for v in services.values())
    print(f"{'all services':30} {total_cpu:16.1f} " + " ".join(f"{split_total[k]:{w}.1f}" for k, w in
                                                               zip(kinds, (6, 5, 6, 6)))
          + f" {sum(v[1] for v in services.values()):8.1f} {total_pss:8.1f}")
    for name, (cpu, rss, pss) in usage.items():
        if name.startswith("("):
            print(f"{name:30} {cpu:16.1f} {'':27} {rss:8.1f} {pss:8.1f}")
    print(f"aims: services' CPU {total_cpu:.1f} % of one core (aim <= {CPU_AIM_PCT:g}: "
          f"{'met' if total_cpu <= CPU_AIM_PCT else 'not met'}), PSS {total_pss:.0f} MB (aim <= {PSS_AIM_MB:g}: "
          f"{'met' if total_pss <= PSS_AIM_MB else 'not met'}); loop = the service's own thread (its driver "
          "loop or timer), bus = the bus handler thread (decode, verify, callbacks), health = its Health publisher")
    print(f"\n{'channel':28} {'msg/s':>8} {'kB/s':>8}")
    for channel, (n, size) in sorted(counts.items(), key=lambda kv: -kv[1][0]):
        print(f"{channel:28} {n / window:8.1f} {size / window / 1000:8.2f}")
    total = sum(n for n, _ in counts.values())
    print(f"{'all channels':28} {total / window:8.1f} {sum(s for _, s in counts.values()) / window / 1000:8.2f}")


# -- phase 2: latency ---------------------------------------------------------------------
def quiet_copy(vehicle: Path, into: Path) -> Path:
    """The vehicle with sensor noise off, control integrators off, one waypoint straight ahead."""
    shutil.copytree(vehicle.parent, into, ignore=shutil.ignore_patterns("data", "logs"))
    path = into / vehicle.name
    profile = tomllib.loads(path.read_text())
    noise_off = {"nmea_gps": {"horizontal_sigma_m": 0.0, "vertical_sigma_m": 0.0, "speed_sigma_mps": 0.0,
                              "heading_sigma_deg": 0.0},
                 "nmea_compass": {"heading_sigma_deg": 0.0, "attitude_sigma_deg": 0.0},
                 "mpu9250": {"gyro_noise_dps": 0.0, "accel_noise_g": 0.0}}
    for device in profile.get("devices", {}).values():
        device.setdefault("options", {}).update(noise_off.get(device.get("mock"), {}))
    path.write_text(tomli_w.dumps(profile))
    control = into / "config" / "control.toml"
    settings = tomllib.loads(control.read_text()) | {"heading_ki": 0.0, "speed_ki": 0.0}
    control.write_text(tomli_w.dumps(settings))
    (into / "mission.xml").write_text(LATENCY_MISSION)
    return path


class StageListener:
    """Receive times of the messages between the GPS and the motors."""

    def __init__(self, url: str) -> None:
        self.info: list[float] = []
        self.estimate: list[float] = []
        self.nav: list[tuple[float, tuple[float, float]]] = []
        self.cmd: list[tuple[float, str, float]] = []
        self.transport = Transport(url, name="bench-stages")
        self.transport.subscribe(ch.STATE_INFO, t.StateInformation, self._on_info)
        self.transport.subscribe(ch.STATE_ESTIMATE, t.StateInformation,
                                 lambda _c, _m: self.estimate.append(time.monotonic()))
        self.transport.subscribe(ch.NAV_POINT, t.NavigationPoint,
                                 lambda _c, m: self.nav.append((time.monotonic(), (m.x, m.y))))
        self.transport.subscribe(ch.ACTUATOR_CMD, t.PercentageCommand,
                                 lambda _c, m: self.cmd.append((time.monotonic(), m.base.actuator_name, m.percentage)))
        self.transport.start()

    def _on_info(self, _c: str, msg: t.StateInformation) -> None:
        if msg.header.source == "gps":
            self.info.append(time.monotonic())


def first_after(times: list[float], t0: float) -> float | None:
    return next((x for x in times if x > t0), None)


def first_changed_command(cmds: list[tuple[float, str, float]], after: float) -> tuple[float, float] | None:
    """(receive time, percentage) of the first ACTUATOR_CMD after *after* that differs from its actuator's previous one."""
    last: dict[str, float] = {}
    for tc, name, value in cmds:
        if tc > after and name in last and abs(value - last[name]) > 1e-6:
            return tc, value
        last[name] = value
    return None


def frame_carrying(vels: dict[int, list[tuple[float, float]]], percent: float, *, after: float,
                   max_turns: float) -> float | None:
    """When the mock ODrives first received, after *after*, the Set_Input_Vel that carries *percent*.

    Matched by value (|rev/s| = |percent| / 100 * max_turns): this process's bus listener gets
    a command a little after the driver does, so "the first frame after the command's receive
    time" can miss the very frame the command caused.
    """
    want = abs(percent) / 100.0 * max_turns
    hits = [t for rows in vels.values() for (t, v) in rows if t > after and abs(abs(v) - want) < 1e-4]
    return min(hits, default=None)


def set_input_vels(nodes: list[Any]) -> dict[int, list[tuple[float, float]]]:
    """node id -> [(t, rev/s)] of the Set_Input_Vel frames each mock ODrive received."""
    out: dict[int, list[tuple[float, float]]] = {}
    for node in nodes:
        rows = []
        for rec in node.history:
            if rec.direction == "rx" and not rec.message.is_remote_frame:
                node_id, cmd = cs.split_arbitration_id(rec.message.arbitration_id)
                if cmd == cs.Cmd.SET_INPUT_VEL:
                    rows.append((rec.t, cs.decode_floats(bytes(rec.message.data), 2)[0]))
        out[node.node_id] = rows
    return out


def latency_phase(vehicle: Path, out: Path, *, seconds: float, threshold: float, realtime: bool) -> None:
    work = Path(tempfile.mkdtemp(prefix="u2sa-bench-"))
    run = SimRun(options(quiet_copy(vehicle, work / "vehicle"), out / "latency", realtime=realtime),
                 progress=ProgressLine(interactive=False, plain_every_s=60))
    try:
        max_turns = float(tomllib.loads((work / "vehicle" / "config" / "wheels.toml").read_text())
                          .get("max_turns_per_s", 5.0))
        run.start()
        run.mocks.actuated.hold(True)
        gps = run.mocks.device("gps").parts[0]
        stepping = threading.Event()
        offset = {"east": 0.0}
        solve = gps.solve

        def stepped(truth: Any) -> Any:   # called once per epoch: while stepping, every epoch jumps
            if stepping.is_set():
                offset["east"] = STEP_M - offset["east"]
            return solve(dataclasses.replace(truth, east=truth.east + offset["east"]))

        gps.solve = stepped
        run.wait_ready()
        run.engage()
        stages = StageListener(run.monitor.transport.url)
        time.sleep(5.0)   # the estimate and the commands settle
        start = time.monotonic()
        stepping.set()
        time.sleep(seconds)
        end = time.monotonic()
        stepping.clear()
        stages.transport.stop()
        epochs = [line.t for line in gps.history if line.text[3:6] == "GGA" and start <= line.t <= end]
        vels = set_input_vels(list(run.mocks.context.can_nodes.values()))
    finally:
        run.record.result, run.record.reason = "stopped", "latency benchmark: the vehicle was held still"
        run.finish()
        shutil.rmtree(work, ignore_errors=True)
    chain, totals, per_stage, missed, noncausal, effects = [], [], defaultdict(list), 0, 0, []
    for t0, t_next in zip(epochs, epochs[1:] + [end]):
        # The causal chain: each stage's first output after its input (the first NAV_POINT and
        # ACTUATOR_CMD that changed), then the frame the mock ODrives received that carries that
        # command (the driver sends at once). Noise is off, so a change is this epoch's doing.
        t_info = first_after(stages.info, t0)
        t_est = first_after(stages.estimate, t_info) if t_info else None
        t_nav = next((tn for (tn, _p), (_tp, prev) in zip(stages.nav[1:], stages.nav) if t_est and tn > t_est
                      and _p != prev), None)
        cmd = first_changed_command(stages.cmd, t_nav) if t_nav else None
        t_cmd = cmd[0] if cmd else None
        t_frame = frame_carrying(vels, cmd[1], after=t0, max_turns=max_turns) if cmd else None
        for name, a, b in (("NMEA -> STATE_INFO (gps driver)", t0, t_info),
                           ("STATE_INFO -> STATE_ESTIMATE (estimator)", t_info, t_est),
                           ("STATE_ESTIMATE -> NAV_POINT (planner)", t_est, t_nav),
                           ("NAV_POINT -> ACTUATOR_CMD (control)", t_nav, t_cmd),
                           ("ACTUATOR_CMD -> CAN frame (odrive driver)", t_cmd, t_frame)):
            if a is not None and b is not None and b >= a:
                per_stage[name].append(b - a)
        if t_frame is not None and t_frame < t_next:
            chain.append(t_frame - t0)
        # The black-box check: the first Set_Input_Vel that moved by more than --threshold. It
        # includes the controller's own dynamics: an epoch whose first command moved a wheel by
        # less than the threshold is counted at the next control cycle that moves it more.
        t1, size = None, 0.0
        for rows in vels.values():
            before = [v for (t, v) in rows if t <= t0]
            if not before:
                continue
            hit = next(((t, abs(v - before[-1])) for (t, v) in rows if t0 < t < t_next and abs(v - before[-1]) > threshold),
                       None)
            if hit and (t1 is None or hit[0] < t1):
                t1, size = hit
        if t1 is None:
            missed += 1
        elif t_info is None or t1 < t_info:
            noncausal += 1   # the motors changed before the GPS driver had published: not this epoch's doing
        else:
            totals.append(t1 - t0)
            effects.append(size)
    print(f"\n== latency: {len(epochs)} GPS epochs over {seconds:g} s; the causal chain found in {len(chain)}")
    if chain:
        print(f"{'NMEA written -> resulting Set_Input_Vel':44} p50 {1e3 * pct(chain, 0.5):6.1f} ms   "
              f"p99 {1e3 * pct(chain, 0.99):6.1f} ms   max {1e3 * max(chain):6.1f} ms")
    for name, values in per_stage.items():
        print(f"  {name:42} p50 {1e3 * pct(values, 0.5):6.1f} ms   p99 {1e3 * pct(values, 0.99):6.1f} ms"
              f"   mean {1e3 * statistics.fmean(values):6.1f} ms")
    print(f"black box: first Set_Input_Vel moved by more than {threshold:g} rev/s after an epoch: {len(totals)} epochs, "
          f"{missed} without, {noncausal} with a change before the GPS driver published (not counted)")
    if totals:
        print(f"  effect (rev/s): min {min(effects):.4f}, p10 {pct(effects, 0.1):.4f}, p50 {pct(effects, 0.5):.4f}; "
              f"latency p50 {1e3 * pct(totals, 0.5):.1f} ms, p99 {1e3 * pct(totals, 0.99):.1f} ms "
              "(includes the controller's own dynamics)")


def main() -> int:
    use_run_key()   # without an installed key, a fresh one for this run and the services it starts
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicle", type=Path, default=REPO / "examples" / "ground_vehicle" / "vehicle.toml")
    parser.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "u2sa-bench-stack")
    parser.add_argument("--latency-s", type=float, default=30.0, help="seconds of GPS steps (default 30)")
    parser.add_argument("--threshold", type=float, default=2e-3, help="rev/s change that counts as an effect")
    parser.add_argument("--skip-mission", action="store_true")
    parser.add_argument("--skip-latency", action="store_true")
    parser.add_argument("--no-realtime", action="store_true",
                        help="run the safety chain and the sim process at normal priority (as u2sa sim --no-realtime)")
    args = parser.parse_args()
    print(f"u2sa-hw stack benchmark: {args.vehicle}, {psutil.cpu_count()} CPUs, "
          f"load average {', '.join(f'{x:.1f}' for x in psutil.getloadavg())}")
    if not args.skip_mission:
        mission_phase(args.vehicle, args.out, realtime=not args.no_realtime)
    if not args.skip_latency:
        latency_phase(args.vehicle, args.out, seconds=args.latency_s, threshold=args.threshold,
                      realtime=not args.no_realtime)
    return 0


if __name__ == "__main__":
    sys.exit(main())
