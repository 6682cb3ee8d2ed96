"""``u2sa sim``: the mock devices, the whole stack through the launcher, a pilot, a mission.

:class:`SimRun` does it in steps a benchmark can interleave with its own::

    run = SimRun(SimOptions(vehicle=Path("examples/ground_vehicle/vehicle.toml"), out=Path("sim-out")))
    run.start()                 # mocks, simulation profile, bus monitor, launcher (all services)
    run.wait_ready()            # every service up, a pose estimate, a mission, the RC mux in manual
    run.engage()                # the pilot flips the mode switch: autonomous
    run.drive()                 # until the mission completes, a service fails, or the timeout
    summary = run.finish()      # stop everything; summary.json/.txt, track.csv, track.png

``run()`` chains them. The simulated vehicle lives in this process (with the mocks), so
its true track is sampled here, at ``SAMPLE_HZ``. With a scenario (``SimOptions.scenario``,
:mod:`u2sa_hw.simulation.events`) ``run()`` plays its events instead of waiting for the mission's
end, a failsafe or a loss of autonomy is what the run is about rather than a failure, and
the summary says what each event did to every actuator output (:mod:`u2sa_hw.simulation.effects`).

The pilot hands over only once every IMU has calibrated at rest (its health ``ok``): the
vehicle stands still in manual with the sticks centred until then.
"""

from __future__ import annotations

import math
import os
import shutil
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from u2sa_hw.simulation.effects import final_outputs
from u2sa_hw.simulation.events import Scenario, load_scenario_file
from u2sa_hw.simulation.profile import effective_configs, write_sim_profile
from u2sa_hw.simulation.progress import (BusMonitor, BusSnapshot, ProgressLine, control_mode, mission_done,
                                rc_state_name, status_text)
from u2sa_hw.simulation.readiness import SimFailure, not_ready, where
from u2sa_hw.simulation.scenario import load_scenario
from u2sa_hw.simulation.script import ScriptRunner
from u2sa_hw.simulation.summary import (RunRecord, run_title, summarise, summary_text, track_sample, write_summary,
                                        write_track_csv)
from u2sa_hw.launcher import Launcher, RestartPolicy
from u2sa_hw.realtime import SIM_DEVICES_PRIORITY, ProcessPriority, plan
from u2sa_hw.profile.loader import load_profile

# "off": every u2sa sim of this environment at normal priority, as --no-realtime. The test suite
# sets it: two simulations side by side (pytest-xdist) at one SCHED_FIFO priority do not share a
# CPU by time slices as normal tasks do, so one's busy moment stalls the other's simulated RC
# receiver, a false NO RC SIGNAL. One stack on a board has no such neighbour.
SIM_REALTIME_ENV = "U2SA_SIM_REALTIME"


def sim_realtime_allowed() -> bool:
    """False when ``$U2SA_SIM_REALTIME`` is "off" (or 0, no, false)."""
    return os.environ.get(SIM_REALTIME_ENV, "").strip().lower() not in ("off", "0", "no", "false")


SAMPLE_HZ = 10.0
TICK_S = 0.2
REARM_AFTER_S = 1.0       # the pilot re-arms when RC_MODE still says "not armed" this long after the switch
REARM_TRIES = 5
MAX_INTERRUPTIONS = 3   # autonomy lost and re-engaged by the pilot at most this often
ERROR_MARKERS = (" ERROR ", " CRITICAL ", "Traceback (most recent call last)")


@dataclass
class SimOptions:
    """What ``u2sa sim`` was asked for."""

    vehicle: Path
    out: Path = Path("sim-out")
    mission: Path | None = None
    timeout_s: float | None = None     # None: the profile's [simulation] timeout_s
    record: bool = False
    lcm_url: str | None = None          # None: the profile's
    can_port: int | None = None         # None: the profile's [simulation] can_udp_port
    grace_s: float = 3.0
    scenario: Path | None = None        # a failsafe scenario file (u2sa_hw.simulation.events)
    service_cgroup: Path | None = None  # every service (each restart too) joins this cgroup; the mocks stay out
    realtime: bool = True               # the safety chain and this process (the mocks) SCHED_FIFO, when permitted


class SimRun:
    """One simulation run (see the module docstring)."""

    def __init__(self, options: SimOptions, *, progress: ProgressLine | None = None) -> None:
        self.options = options
        self.progress = progress or ProgressLine()
        self.out = options.out.resolve()
        self.profile = load_profile(options.vehicle)
        self.configs = effective_configs(self.profile)
        self.scenario = load_scenario(self.profile, self.configs, mission=options.mission)
        self.script: Scenario | None = load_scenario_file(options.scenario) if options.scenario else None
        self.player: ScriptRunner | None = None
        self.t0: float | None = None    # when the scenario's clock started
        self.imus = [n for n, spec in self.profile.services.items() if spec.enabled and spec.kind.startswith("imu_")]
        self.mocks: Any = None
        self.monitor: BusMonitor | None = None
        self.launcher: Launcher | None = None
        self.realtime = plan(enabled=options.realtime and sim_realtime_allowed())
        self._priority: ProcessPriority | None = None   # this process's raise, undone by stop()
        self.record = RunRecord(vehicle=self.profile.name, mission=self.scenario.mission_name,
                                looping=self.scenario.looping, goals=self.scenario.goals,
                                obstacles=self.scenario.obstacles, fence=self.scenario.fence,
                                t_start=time.monotonic())
        self.deadline = math.inf
        self._stop_sampling = threading.Event()
        self._sampler: threading.Thread | None = None
        self._services_log: Any = None
        self._tmp_device_dir: Path | None = None
        self._stopping = False
        self._said: dict[str, str] = {}   # service -> the health error last shown on the console

    # -- steps ---------------------------------------------------------------------------
    def start(self) -> None:
        """Start the mocks, write the simulation profile, listen to the bus, launch the services."""
        from u2sa_hw.mocks.launcher import MockLauncher
        from u2sa_hw.mocks.sim_context import device_dir_for

        for sub in ("run", "logs"):
            shutil.rmtree(self.out / sub, ignore_errors=True)
        run_dir = self.out / "run"
        device_dir = device_dir_for(run_dir / "dev")
        if not device_dir.is_relative_to(self.out):
            self._tmp_device_dir = device_dir
        self.mocks = MockLauncher(self.profile, device_dir=device_dir, service_configs=self.configs,
                                  can_udp_port=self.options.can_port, check_inputs=True)
        timeout = self.options.timeout_s or self.mocks.settings.timeout_s
        self.deadline = self.record.t_start + timeout
        # This process hosts the mock devices: real-time below the safety chain, since a real RC receiver or
        # motor controller does not stall when the board is busy (a stalled mock is a false NO RC SIGNAL).
        self._priority = self.realtime.raise_process(SIM_DEVICES_PRIORITY)
        self.mocks.start()
        record_dir = self.out / "recording" if self.options.record else None
        overrides: dict[str, dict[str, Any]] = {}
        if record_dir is not None:   # the drivers tap their ports too, so the recording can be replayed
            for name in (n for n, c in self.configs.items() if "record_raw" in c):
                overrides.setdefault(name, {})["record_raw"] = True
        sim_profile_path = write_sim_profile(self.profile, run_dir=run_dir, addresses=self.mocks.addresses,
                                             overrides=overrides, log_dir=self.out / "logs", lcm_url=self.options.lcm_url,
                                             mission=self.scenario.mission_file, record_dir=record_dir)
        sim_profile = load_profile(sim_profile_path)
        self.monitor = BusMonitor(sim_profile.lcm_url)
        self._say_start(sim_profile, timeout)
        for line in filter(None, [self.realtime.notice or self._priority.refused]):
            self.progress.event(f"  {line}")
        self._services_log = (self.out / "services.log").open("w", buffering=1)
        self.launcher = Launcher(sim_profile, grace_s=self.options.grace_s, output=self._on_output,
                                 policy=RestartPolicy(initial_backoff_s=0.5, give_up_after=3),
                                 on_death=self._on_death, cgroup=self.options.service_cgroup,
                                 realtime=self.realtime)
        if self.script is not None:
            self.player = ScriptRunner(self.script, self)
            self.player.check()
        self.launcher.start()
        self._sampler = threading.Thread(target=self._sample, name="sim-sampler", daemon=True)
        self._sampler.start()

    def wait_ready(self) -> None:
        """Wait until the stack can drive: SimFailure (timeout or failed) otherwise."""
        while True:
            snap = self._check()
            missing = not_ready(snap, names=list(self.launcher.processes), imus=self.imus, said=self._said,
                                waited_s=time.monotonic() - self.record.t_start, say=self.progress.event)
            if not missing:
                degraded = sorted(n for n, (status, _e, _t) in snap.health.items()
                                  if n in self.launcher.processes and status != "ok")
                self.progress.event(f"ready after {time.monotonic() - self.record.t_start:.1f} s: "
                                    f"{len(self.launcher.processes)} services up"
                                    + (f" ({', '.join(degraded)} still degraded)" if degraded else "")
                                    + ", pose estimate, mission loaded, RC in manual")
                return
            self._tick(f"[{time.monotonic() - self.record.t_start:5.1f} s] starting: " + "; ".join(missing),
                       waiting_for="the stack to start: " + "; ".join(missing))

    def engage(self) -> None:
        """The pilot flips the RC mode switch to autonomous; waits for the mux to hand over.

        A pilot who sees RC_MODE say "not armed" (a pre-arm check that failed just after the
        switch disarms the rc service), or a refusal whose fix is a re-arm through manual (a
        motor controller's watchdog trip of its driver's own stall), re-arms through manual, at
        most REARM_TRIES times.
        """
        self.mocks.set_mode_switch(True)
        self.progress.event("pilot: RC mode switch -> AUTONOMOUS")
        flipped, tries = time.monotonic(), 0
        while True:
            snap = self._check()
            if snap.autonomous_since is not None:
                if self.record.t_engage is None:
                    self.record.t_engage = snap.autonomous_since
                return
            state = rc_state_name(snap.rc) if snap.rc is not None else "no RC_MODE"
            told = "not armed" in state or "to clear: switch through manual" in state   # a refusal's own fix
            if told and time.monotonic() - flipped > REARM_AFTER_S and tries < REARM_TRIES:
                tries += 1
                self.progress.event(f"pilot: RC_MODE says {state}: re-arming through manual")
                self._to_manual()
                self.mocks.set_mode_switch(True)
                flipped = time.monotonic()
                continue
            self._tick(f"[{time.monotonic() - self.record.t_start:5.1f} s] waiting for RC_MODE autonomous ({state})",
                       waiting_for=f"RC_MODE to report autonomous with autonomy enabled (RC_MODE: {state})")

    def _to_manual(self) -> None:
        self.mocks.set_mode_switch(False)
        while True:
            snap = self._check()
            if snap.rc is not None and snap.rc.mode == 0:
                return
            self._tick(f"[{time.monotonic() - self.record.t_start:5.1f} s] waiting for RC_MODE manual",
                       waiting_for="RC_MODE manual for the pilot to re-arm")

    def reengage(self, tick: Any = None) -> None:
        """The safety pilot's procedure: mode switch to manual, wait for RC_MODE manual, then engage."""
        self.progress.event("pilot: RC mode switch -> MANUAL (to re-arm)")
        self._to_manual()
        self.engage()

    def _reengage(self, snap: BusSnapshot) -> None:
        """Autonomy dropped (the mux's side of it): the safety pilot re-arms through manual and hands back."""
        rc = snap.rc
        why = f"RC_MODE {rc.mode_name or rc.mode}, autonomy enabled {rc.autonomy_enabled}" if rc else "no RC_MODE"
        self.record.interruptions.append({"at_s": round(time.monotonic() - self.record.t_engage, 2), "why": why})
        if len(self.record.interruptions) > MAX_INTERRUPTIONS:
            raise SimFailure(f"the vehicle left autonomous mode {len(self.record.interruptions)} times "
                             f"(last: {why})")
        self.progress.event(f"  ! autonomy lost ({why}): the pilot switches to manual and back")
        self._to_manual()
        self.engage()

    def drive(self) -> None:
        """Follow the mission until it completes (one full loop for a looping one, see :func:`loop_completed`)."""
        reported = 0
        total = len(self.scenario.goals)
        while True:
            snap = self._check()
            if snap.autonomous_since is None:
                self._reengage(snap)
                continue
            before = [i for i, c in enumerate(snap.changes) if c.t < self.record.t_engage]
            changes = snap.changes[before[-1] if before else 0:]   # from the goal current when engaging
            for previous, change in zip(changes[reported:], changes[reported + 1:]):
                if not previous.finished:
                    at = change.t - self.record.t_engage
                    self.progress.event(f"goal {previous.index + 1}/{total} {previous.uid} reached at {at:.1f} s")
            reported = max(reported, len(changes) - 1)
            if mission_done(snap.status, snap.changes, since=self.record.t_engage):
                self.record.result, self.record.reason = "completed", ""
                return
            distance = snap.nav.distance_to_goal if snap.nav is not None and snap.nav.distance_to_goal >= 0 else None
            self._tick(status_text(snap, elapsed=time.monotonic() - self.record.t_engage, goal_total=total,
                                   distance=distance), waiting_for=where(snap, len(self.scenario.goals)))

    def play(self) -> None:
        """Play the scenario's events from t0 (autonomy engaged, or ready when the scenario does not engage)."""
        assert self.player is not None and self.script is not None
        self.t0 = self.record.t_engage if self.script.engage and self.record.t_engage else time.monotonic()
        self.progress.event(f"scenario '{self.script.name}': {len(self.script.events)} events over "
                            f"{self.script.end_s:g} s")

        def tick(what: str) -> None:
            snap = self._check()
            self._tick(f"[{time.monotonic() - self.t0:5.1f} s] {what} | {control_mode(snap)}",
                       waiting_for=f"scenario '{self.script.name}' ({what})")

        self.player.play(self.t0, tick=tick)
        # "completed" is the mission's word: a scenario that played to its end without the goals reached only "played"
        snap = self._check()
        done = mission_done(snap.status, snap.changes, since=self.record.t_engage)
        self.record.result, self.record.reason = "completed" if done else "played", ""

    def run(self) -> dict[str, Any]:
        """All steps; returns the summary (``result`` completed, timeout or failed)."""
        try:
            self.start()
            self.wait_ready()
            if self.script is None:
                self.engage()
                self.drive()
            else:
                if self.script.engage:
                    self.engage()
                self.play()
        except SimFailure as exc:
            self.record.result, self.record.reason = exc.result, str(exc)
        except KeyboardInterrupt:
            self.record.result, self.record.reason = "failed", "interrupted (Ctrl-C)"
        except BaseException:
            self.stop()   # a setup error: nothing to summarise, but leave no services or mocks behind
            raise
        return self.finish()

    def finish(self) -> dict[str, Any]:
        """Stop services and mocks; write the summary, the track and the plot; return the summary."""
        self.record.t_end = time.monotonic()
        self.progress.finish()
        self.stop()
        files = []
        self.out.mkdir(parents=True, exist_ok=True)
        files.append(write_track_csv(self.record.samples, self.out / "track.csv"))
        try:
            from u2sa_hw.simulation.plot import plot_run

            files.append(plot_run(self.out / "track.png", samples=self.record.samples, goals=self.scenario.goals,
                                  obstacles=self.scenario.obstacles, t_engage=self.record.t_engage,
                                  title=run_title(self.record), fence=self.scenario.fence))
        except ImportError as exc:   # matplotlib is the "sim" extra
            self.progress.event(f"no plot: {exc} (pip install 'u2sa-hw[sim]')")
        summary = summarise(self.record)
        if self.mocks is not None:
            summary["outputs"] = final_outputs(self.mocks.outputs)
        if self.player is not None:
            rc_modes = self.monitor.snapshot().rc_changes if self.monitor is not None else []
            summary["scenario"] = self.player.summary(self.mocks.outputs, t0=self.t0 or self.record.t_end,
                                                      end=self.record.t_end, rc_modes=rc_modes,
                                                      rc_stalls=self.mocks.rc_stalls())
        json_path, text_path = write_summary(summary, self.out, extra_files=files)
        self.progress.event(summary_text(summary, files=[json_path, text_path, *files]))
        return summary

    def stop(self) -> None:
        """Stop the services (SIGTERM, SIGKILL after the grace), the sampler, the monitor, the mocks."""
        self._stopping = True
        if self.launcher is not None:
            # the recorder stops after the others: each stop may take up to stop_limit_s (then SIGKILL)
            self.launcher.stop(timeout=2 * self.launcher.stop_limit_s + 5.0)
            self.record.services = {s.name: {"state": s.state, "restarts": s.restarts, "last_exit": s.last_exit}
                                    for s in self.launcher.status()}
        self._stop_sampling.set()
        if self._sampler is not None:
            self._sampler.join(timeout=2)
        if self.monitor is not None:
            self.record.changes = self.monitor.snapshot().changes
            self.monitor.close()
        if self.mocks is not None:
            self.mocks.stop()
        if self._services_log is not None:
            self._services_log.close()
            self._services_log = None
        if self._tmp_device_dir is not None:
            shutil.rmtree(self._tmp_device_dir, ignore_errors=True)
        if self._priority is not None:
            self._priority.restore()

    # -- internals -----------------------------------------------------------------------
    def _say_start(self, sim_profile: Any, timeout: float) -> None:
        s = self.scenario
        self.progress.event(f"u2sa sim: {self.profile.name} ({self.mocks.settings.model}), mission '{s.mission_name}' "
                            f"({len(s.goals)} goals{', looping' if s.looping else ''}), "
                            f"{len([x for x in sim_profile.services.values() if x.enabled])} services, "
                            f"timeout {timeout:g} s")
        self.progress.event(f"  bus {self.monitor.transport.url}; output in {self.out}")
        for line in self.mocks.describe():
            self.progress.event(f"  mock {line}")

    def _on_output(self, name: str, line: str) -> None:
        log = self._services_log
        if log is not None:
            try:
                log.write(f"{name:<10} | {line}\n")
            except ValueError:
                pass
        if name != "launcher" and any(marker in line for marker in ERROR_MARKERS):
            self.progress.event(f"  ! {name}: {line[line.find(' ERROR ') + 1:] if ' ERROR ' in line else line}")

    def _on_death(self, status: Any, account: str) -> None:
        if not self._stopping:
            self.progress.event(f"  ! {status.name} {account}")

    def _check(self) -> BusSnapshot:
        """The bus state; SimFailure on a failsafe or a service the launcher gave up."""
        assert self.monitor is not None and self.launcher is not None
        snap = self.monitor.snapshot()
        if self.launcher.failed:
            failed = self.launcher.failed[0]
            status = next(s for s in self.launcher.status() if s.name == failed)
            raise SimFailure(f"service {failed} keeps failing ({status.reason or status.last_exit}); "
                             f"its log: {self.out / 'logs' / (failed + '.log')}")
        if self.launcher.finished.is_set():
            raise SimFailure("every service stopped")
        if snap.failsafe is not None and self.script is None:
            raise SimFailure(f"FAILSAFE from {snap.failsafe.header.source or '?'}: {snap.failsafe.reason}")
        return snap

    def _tick(self, text: str, *, waiting_for: str) -> None:
        self.progress.update(text)
        if time.monotonic() >= self.deadline:
            timeout = self.deadline - self.record.t_start
            raise SimFailure(f"timeout after {timeout:g} s waiting for {waiting_for}", "timeout")
        time.sleep(TICK_S)

    def _sample(self) -> None:
        while not self._stop_sampling.wait(1.0 / SAMPLE_HZ):
            truth = self.mocks.vehicle.snapshot()
            snap = self.monitor.snapshot()
            self.record.samples.append(track_sample(truth, snap, time.monotonic()))
            self.record.changes = snap.changes
