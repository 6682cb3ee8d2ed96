"""``u2sa replay``: run the real drivers (and any core services asked for) against mock devices
that play a log's recorded raw I/O back, and record what they publish.

Steps: plan (hil/replay_plan.py: which service drives which device, the configs, the
overrides) -> a private run directory and LCM URL (a replay never talks to a live vehicle:
``ttl=0`` and a port of its own) -> replay devices at the addresses written into the
drivers' configs -> capture of the replay bus into the output log (the recorder's
BusCapture) -> the services as supervised processes (the launcher) -> wait until every
driver has opened its device -> play (hil/player.py) -> let the last outputs arrive -> stop
-> check the recorded pilot messages (RC_MODE, MANUAL_CMD) of the window with the pilot's public
key the log names (u2sa_hw.recording.pilot_check; ``ReplayResult.pilot``).
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import tomli_w

from u2sa_hw.bus.key import KEY_ENV
from u2sa_hw.bus.run_keys import fresh_key_file
from u2sa_hw.launcher import Launcher, ProcessStatus, RestartPolicy
from u2sa_hw.recording.mcap_log import McapLogWriter, RunInfo
from u2sa_hw.services.recorder.capture import BusCapture
from u2sa_hw.bus.transport import Transport
from u2sa_hw.bus.multicast_check import check_multicast
from u2sa_hw.bus.lcm_open import TransportError
from u2sa_hw.profile.loader import load_profile
from u2sa_hw.bus.udp_ports import private_lcm_url

from u2sa_hw.hil.player import ORDERED_CHANNELS, PlayStats, Player
from u2sa_hw.hil.progress import ProgressBar
from u2sa_hw.hil.replay_buses import make_device   # the replay device of each kind: PORT_KINDS' replay part
from u2sa_hw.hil.replay_devices import ReplayDevice
from u2sa_hw.ports.serial.replay import ReplaySerialDevice, ReplayStalled
from u2sa_hw.hil.replay_i2c import held_drivers, release_held_reads
from u2sa_hw.hil.replay_plan import ReplayError, ReplayPlan, build_plan, write_run_profile
from u2sa_hw.hil.replay_watch import ReplayWatch, discover, listeners


@dataclass
class ReplayOptions:
    """What ``u2sa replay`` was asked for."""

    rate: float = 1.0
    fast: bool = False
    start_s: float = 0.0
    end_s: float | None = None
    services: list[str] = field(default_factory=list)
    overrides: list[str] = field(default_factory=list)
    out: Path | None = None
    vehicle: Path | None = None
    keep_run_dir: bool = False
    progress: bool | None = None          # None: when stderr is a terminal
    ready_timeout_s: float = 30.0
    settle_s: float = 1.0                 # quiet time that ends the replay after the last input
    lcm_url: str | None = None            # default: a free private port (u2sa_hw.bus.udp_ports), ttl=0


@dataclass
class ReplayResult:
    """What a replay did."""

    plan: ReplayPlan
    out: Path
    play: PlayStats
    startup_s: float
    outputs: int                           # messages from the replayed services that reached the recorder
    lost: int                              # ... that the services published but the replay bus lost
    written: int                           # messages in the output log
    dropped: int
    devices: dict[str, dict[str, Any]]
    run_dir: Path | None
    pilot: Any = None                      # u2sa_hw.recording.pilot_check.PilotCheck of the replayed window
    phases: dict[str, float] = field(default_factory=dict)   # wall seconds per step of the run, in order (bench)

    def summary(self, *, fast: bool, rate: float) -> str:
        """The one-line summary printed at the end."""
        played = self.plan.duration_s
        speed = played / self.play.wall_s if self.play.wall_s > 0 else 0.0
        mode = "--fast" if fast else f"--rate {rate:g}"
        return (f"replayed {played:.1f} s of {self.plan.log.name} ({mode}) in {self.play.wall_s:.1f} s "
                f"({speed:.1f}x real time, {self.startup_s:.1f} s starting {len(self.plan.services)} services): "
                f"{self.outputs} messages from {', '.join(self.plan.services)}"
                + (f" ({self.lost} more lost on the replay bus)" if self.lost else "")
                + f"; {self.written} written to {self.out}, {self.dropped} dropped"
                + (f"; {self.play.order_timeouts} recorded messages went out without the replayed "
                   f"{'/'.join(ORDERED_CHANNELS)} state the recording had then (the replay never reached it)"
                   if self.play.order_timeouts else ""))


def private_url(plan: ReplayPlan) -> str:
    """``udpm://239.255.76.67:<private port>?ttl=0``, never the recorded vehicle's port."""
    recorded = plan.summary.contents.metadata.get("u2sa", {}).get("lcm_url", "")
    ports = {int(p) for p in re.findall(r":(\d+)", recorded)}
    return private_lcm_url(avoid=ports)   # the transport adds the receive buffer --fast bursts need


class _Outputs:
    """The services' output lines (the last few per service, for error messages)."""

    def __init__(self, echo: Callable[[str], None] | None) -> None:
        self.lines: dict[str, deque[str]] = {}
        self.echo = echo

    def __call__(self, name: str, line: str) -> None:
        self.lines.setdefault(name, deque(maxlen=12)).append(line)
        if self.echo is not None:
            self.echo(f"{name} | {line}")

    def tail(self, name: str) -> str:
        lines = self.lines.get(name)
        return ("; its last output:\n    " + "\n    ".join(lines)) if lines else ""


class Replay:
    """One replay run; :meth:`run` does everything and cleans up."""

    def __init__(self, path: Path | str, options: ReplayOptions, *, echo: Callable[[str], None] | None = None) -> None:
        self.options = options
        began = time.monotonic()
        self.plan = build_plan(path, extra_services=options.services, overrides=options.overrides,
                               start_s=options.start_s, end_s=options.end_s, vehicle=options.vehicle)
        self.fast, self.rate = options.fast, options.rate   # as played
        self.out = options.out or self.plan.log.with_suffix(".replay.mcap")
        if self.out.resolve() == self.plan.log.resolve():
            raise ReplayError(f"--out {self.out}: the output must not be the log being replayed")
        self.echo = echo
        self.outputs = _Outputs(echo)
        self.abort = threading.Event()
        self._abort_reason = ""
        self._stopping = False
        self.watch = ReplayWatch(self.plan.services)   # what the replay bus shows of the replayed services
        self.run_dir: Path | None = None   # made by run(); kept after a failure for its logs
        self.phases: dict[str, float] = {"plan": time.monotonic() - began}   # see _phase
        self._phase_at = time.monotonic()

    def _phase(self, name: str) -> None:
        """Note the wall time since the previous step as step *name* (ReplayResult.phases; bench/replay.py)."""
        now = time.monotonic()
        self.phases[name] = self.phases.get(name, 0.0) + now - self._phase_at
        self._phase_at = now

    def _log_of(self, service: str) -> Path:
        return (self.run_dir or Path(".")) / "logs" / f"{service}.log"

    # -- pieces ------------------------------------------------------------------------------
    def _fail(self, reason: str) -> None:
        if not self._abort_reason:
            self._abort_reason = reason
        self.abort.set()

    def _on_death(self, status: ProcessStatus, _account: str) -> None:
        if self._stopping:
            return
        self._fail(f"service '{status.name}' died during the replay ({status.last_exit}); its log is "
                   f"{self._log_of(status.name)}{self.outputs.tail(status.name)}")

    def _wait_ready(self, devices: dict[str, ReplayDevice], launcher: Launcher) -> None:
        deadline = time.monotonic() + self.options.ready_timeout_s
        while True:
            if self.abort.is_set():
                raise ReplayError(self._abort_reason)
            pids = {s.name: s.pid for s in launcher.status()}
            waiting = [n for n in self.plan.services if n not in self.watch.health]
            for d in devices.values():
                service = self.plan.devices[d.name].service
                if not d.ready(pids.get(service), self.watch.health.get(service, {})):
                    waiting.append(f"{d.name} (device of {service})")
            if not waiting:
                return
            if time.monotonic() > deadline:
                first = waiting[0].split(" ")[0]
                service = self.plan.devices[first].service if first in self.plan.devices else first
                raise ReplayError(f"not ready after {self.options.ready_timeout_s:g} s: {', '.join(waiting)}; "
                                  f"see {self._log_of(service)}{self.outputs.tail(service)}")
            time.sleep(0.05)

    def _republished_channels(self, url: str, devices: dict[str, ReplayDevice]) -> set[str]:
        """Channels the replayed services subscribe to (their recorded traffic from other sources is replayed),
        but for a service that takes a channel from its replay device instead (*devices*' ``bus_inputs``: the
        RC mux's replay chip hands it the recorded Health, FAILSAFE and STATE_ESTIMATE in order with the
        edges, and it ignores the bus on them): nobody else listening, the copy would only load the bus."""
        from_device: dict[str, set[str]] = {}   # channel -> services whose replay device hands it over
        for name, device in devices.items():
            for channel in getattr(device, "bus_inputs", ()):
                from_device.setdefault(channel, set()).add(self.plan.devices[name].service)
        self.watch.listeners = listeners(discover(url, self.plan.services), self.plan.services, from_device)
        return {c for c, who in self.watch.listeners.items() if who}

    def _attachments(self, profile_path: Path) -> dict[str, bytes]:
        out = {"vehicle.toml": profile_path.read_bytes()}
        for name in self.plan.services:
            out[f"config/{name}.toml"] = (self.run_dir / "config" / f"{name}.toml").read_bytes()
        o = self.options
        out["replay.toml"] = tomli_w.dumps({"replay": {
            "source": str(self.plan.log.resolve()), "fast": self.fast, "rate": self.rate, "start_s": o.start_s,
            "end_s": -1.0 if o.end_s is None else o.end_s, "overrides": list(o.overrides),
            "services": list(self.plan.services), "devices": [d for d in self.plan.devices
                                                              if self.plan.devices[d].service]}}).encode()
        return out

    def check_pilot(self) -> Any:
        """The recorded pilot messages of the window checked with the log's recorded pilot key (PilotCheck)."""
        from u2sa_hw.recording.log_reader import LogError
        from u2sa_hw.recording.pilot_check import PilotCheck, check_log

        try:
            return check_log(self.plan.log, start_ns=self.plan.start_ns, end_ns=self.plan.end_ns)
        except LogError as exc:   # the log was read to plan the replay: only a file changed meanwhile
            return PilotCheck(note=f"cannot read the log ({exc})")

    # -- the run -----------------------------------------------------------------------------------
    def run(self) -> ReplayResult:
        """Replay; ReplayError (or ReplayStalled) with the reason on failure."""
        o = self.options
        self._phase_at = time.monotonic()
        self.run_dir = Path(tempfile.mkdtemp(prefix="u2sa-replay-"))
        keep = o.keep_run_dir
        url = o.lcm_url or private_url(self.plan)
        try:
            check_multicast(url)
        except TransportError as exc:
            raise ReplayError(str(exc)) from None
        # The run's private bus gets a key of its own, as a simulation's does: the log holds
        # verified payloads, so it replays here whatever key recorded it.
        saved_key = os.environ.get(KEY_ENV)
        os.environ[KEY_ENV] = str(fresh_key_file(self.run_dir))
        devices: dict[str, ReplayDevice] = {}
        launcher: Launcher | None = None
        transport: Transport | None = None
        capture: BusCapture | None = None
        try:
            changes: dict[str, dict[str, Any]] = {}
            addresses: dict[str, str] = {}
            rigs: dict[str, Any] = {}
            later: list[Callable[..., None]] = []   # preloads the device's start does not need (see below)
            for dev in self.plan.devices.values():
                if dev.service:
                    devices[dev.name] = make_device(dev, self.run_dir, self.plan.services[dev.service],
                                                    fast=self.fast, rigs=rigs)
                    preload = getattr(devices[dev.name], "preload", None)
                    if preload is not None and isinstance(devices[dev.name], ReplaySerialDevice):
                        later.append(preload)
                    elif preload is not None:
                        preload(self.plan.log, start_ns=self.plan.start_ns, end_ns=self.plan.end_ns)
                    addresses[dev.name] = devices[dev.name].mock_address(dev.address)
                    changes.setdefault(dev.service, {}).update(devices[dev.name].config_changes())
            self._phase("devices")
            profile_path = write_run_profile(self.plan, self.run_dir, lcm_url=url, changes=changes,
                                             addresses=addresses)
            profile = load_profile(profile_path)
            transport = Transport(url, name="u2sa-replay")
            self.out.parent.mkdir(parents=True, exist_ok=True)
            writer = McapLogWriter(self.out.parent, path=self.out, run=RunInfo(
                vehicle=f"{profile.name} (replay)", system_id=profile.system_id, lcm_url=url,
                attachments=self._attachments(profile_path)))
            capture = BusCapture(transport, writer, min_free_mb=50)
            transport.subscribe(".*", None, self.watch.on_message, raw=True)
            capture.start()
            transport.start()
            self.watch.clocked = any(getattr(d, "timed", False) for d in devices.values())
            for device in devices.values():
                device.start()
            self._phase("bus")
            started = time.monotonic()
            unwatched = held_drivers(devices, {n: d.service or "" for n, d in self.plan.devices.items()})
            launcher = Launcher(profile, only=list(self.plan.services), grace_s=3.0, control=False,
                                output=self.outputs, on_death=self._on_death, unwatched=unwatched,
                                policy=RestartPolicy(initial_backoff_s=0.5, max_backoff_s=0.5, quick_death_s=1e9,
                                                     give_up_after=1))
            launcher.start()
            # The rest of the log reading while the services start (seconds of interpreter start-up and imports
            # in processes of their own): a serial device's preload only notes the recorded silences the player
            # merges in (clock_ticks); it touches neither the bus nor the devices the drivers are opening.
            for preload in later:
                preload(self.plan.log, start_ns=self.plan.start_ns, end_ns=self.plan.end_ns)
            self._phase("log read while starting")
            self._wait_ready(devices, launcher)
            self._phase("services")
            republish = self._republished_channels(url, devices)
            self._phase("discover")
            startup_s = time.monotonic() - started
            bar = ProgressBar(self.plan.duration_s, enabled=o.progress)
            player = Player(self.plan.log, devices=devices, transport=transport, republish=republish,
                            replayed_services=set(self.plan.services), start_ns=self.plan.start_ns,
                            end_ns=self.plan.end_ns, rate=None if self.fast else self.rate, abort=self.abort,
                            abort_reason=lambda: self._abort_reason, progress=bar.update,
                            replayed_state=self.watch.replayed_state.get)
            try:
                stats = player.run()
            except RuntimeError as exc:
                if isinstance(exc, ReplayStalled) and self._abort_reason:
                    raise ReplayError(self._abort_reason) from None
                raise ReplayError(str(exc)) from None
            finally:
                bar.close()
            self._phase("play")
            # the pilot check reads the recorded window again: in the settle's quiet time, when this process
            # only waits (it has no part in what the services publish)
            pilot: list[Any] = []   # its PilotCheck, or what it raised

            def check() -> None:
                try:
                    pilot.append(self.check_pilot())
                except BaseException as exc:  # noqa: BLE001 - raised below, in this thread
                    pilot.append(exc)

            checker = threading.Thread(target=check, name="u2sa-replay-pilot", daemon=True)
            checker.start()
            self.watch.settle(stats.republished_on, o.settle_s, abort=self.abort, reason=lambda: self._abort_reason)
            self._phase("settle")
            checker.join()
            if isinstance(pilot[0], BaseException):
                raise pilot[0]
            self._phase("pilot check (after the settle)")
            self._stopping = True
            # the capture first, as a recording ends: what a driver says while it is being stopped
            # (the RC mux's last RcMode, "stopping") is not part of the run
            capture.stop()
            s = capture.stats
            capture = None
            self._phase("capture stop")
            release_held_reads(devices)
            launcher.stop(timeout=launcher.stop_limit_s + 5.0)
            launcher = None
            self._phase("services stop")
            received = sum(self.watch.received.values())
            lost = max(0, sum(self.watch.published.values()) - received)
            result = ReplayResult(self.plan, self.out, stats, startup_s, received, lost, s.written, s.dropped,
                                  {n: d.report() for n, d in devices.items()}, self.run_dir if keep else None,
                                  pilot[0], self.phases)
            return result
        except BaseException:
            keep = True
            raise
        finally:
            self._stopping = True
            if launcher is not None:
                release_held_reads(devices)
                launcher.stop(timeout=launcher.stop_limit_s + 5.0)
            if capture is not None:
                capture.stop()
            if transport is not None:
                transport.stop()
            for device in devices.values():
                device.stop()
            if saved_key is None:
                os.environ.pop(KEY_ENV, None)
            else:
                os.environ[KEY_ENV] = saved_key
            if not keep:
                shutil.rmtree(self.run_dir, ignore_errors=True)
            self._phase("clean-up")

