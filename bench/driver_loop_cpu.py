#!/usr/bin/env python3
"""CPU of two drivers' own loops per event, in this process, against their real mock devices.

Issue 27 part 1 (a lean stack) counts what each service's own loop thread costs. This bench runs
the real driver code on the example rover's profile (a copy whose ``rc`` and ``imu`` device
addresses point at mocks started here) and measures the CPU time of the driver's loop thread
(``pthread_getcpuclockid``: the thread's own clock, nanoseconds, not the process's):

- ``rc`` (kind rc_mux): the mock RC receiver at 50 Hz (3 channels, 300 edges/s) and the mux
  model on a mock GPIO chip; the pilot arms through manual, then switches to autonomous, as in the
  mission. The pre-arm evidence the bus would bring is fed to the driver's own callbacks from a
  thread of its own: a Health of every watched service once a second and a STATE_ESTIMATE at
  20 Hz (the example's estimator rate). Reported: CPU per edge and per second of the loop
  thread, and of the mock port's reader thread (``gpio-mock-rc``, the same process).
- ``imu`` (kind imu_mpu9250): an MPU-9250 and its AK8963 on a mock I2C bus. First N samples back to
  back (``sample_once`` in this thread: deterministic, no timer), then the real ``run`` loop at
  ``rate_hz`` for the window. Reported: CPU per sample and per second at the live rate.

What is published is counted (and encoded, as a transport would), not sent: the bus's own cost
is the transport's. ``--profile`` prints the top of a cProfile of the loop thread.

Usage: ``python bench/driver_loop_cpu.py [--only rc|imu] [--seconds 20] [--samples 2000] [--profile]``.
Not a test: nothing asserts.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from u2sa_hw.mocks.gpio_chip import MockGpioChip  # noqa: E402
from u2sa_hw.mocks.i2c_bus import MockI2cBus  # noqa: E402
from u2sa_hw.mocks.mpu9250_chip import Ak8963Chip, Mpu9250Chip  # noqa: E402
from u2sa_hw.mocks.rc_receiver import MuxMock, RcReceiverMock  # noqa: E402
from u2sa_hw import lcmtypes as t  # noqa: E402
from u2sa_hw.service.health import set_details  # noqa: E402
from u2sa_hw.bus.run_keys import use_run_key  # noqa: E402
from u2sa_hw.bus.transport import Transport  # noqa: E402
from u2sa_hw.bus.udp_ports import private_lcm_url  # noqa: E402
from u2sa_hw.profile.loader import load_profile  # noqa: E402

EXAMPLE = REPO / "examples" / "ground_vehicle"
RC_LINES = {"throttle": 5, "steering": 6, "mode": 13}
ENABLE, SELECT = 21, 20


def rover_profile(into: Path, *, gpio_sock: Path, i2c_sock: Path, select_line: int = SELECT) -> Any:
    """The example rover's profile, copied, with the rc and imu devices on the mocks at these sockets."""
    shutil.copytree(EXAMPLE, into, dirs_exist_ok=True)
    path = into / "vehicle.toml"
    text = path.read_text().replace("select_line = 20", f"select_line = {select_line}")
    text = text.replace('address = "gpio://gpiochip0/5,6,13,20,21"',
                        f'address = "mock+gpio://{gpio_sock}/5,6,13,20,21"')
    text = text.replace('address = "i2c://1/0x68"', f'address = "mock+i2c://{i2c_sock}/0x68"')
    path.write_text(text)
    return load_profile(path)


def thread_cpu_s(thread: threading.Thread) -> float:
    """CPU seconds *thread* has used (its own clock)."""
    assert thread.ident is not None
    return time.clock_gettime(time.pthread_getcpuclockid(thread.ident))


def find_thread(prefix: str) -> threading.Thread | None:
    """The live thread whose name starts with *prefix*."""
    return next((th for th in threading.enumerate() if th.name.startswith(prefix)), None)


def capture_publish(counts: dict[str, int]) -> Callable[..., bool]:
    """A stand-in for ``publish``: encodes and counts per channel."""
    def publish(channel: str, msg: Any, **_: Any) -> bool:
        msg.encode()
        counts[channel] = counts.get(channel, 0) + 1
        return True
    return publish


def run_profiled(target: Callable[[], None], profile: cProfile.Profile | None) -> Callable[[], None]:
    """*target*, under *profile* when one is given."""
    if profile is None:
        return target
    return lambda: profile.runcall(target)


def print_profile(profile: cProfile.Profile | None, title: str) -> None:
    """The top 25 functions of *profile* by own time."""
    if profile is None:
        return
    out = io.StringIO()
    pstats.Stats(profile, stream=out).sort_stats("tottime").print_stats(25)
    print(f"--- cProfile of {title} (by own time) ---")
    print(re.sub(r"/[^ ]*/(work/main|site-packages)/", "", out.getvalue()))


# ------------------------------------------------------------------ the mocks' process ----------------
def serve_mocks(kind: str, socket_path: str) -> int:
    """The mock devices of *kind* on *socket_path*, in this process (the bench's child, as ``u2sa sim``
    hosts them apart from the services); ``auto`` / ``manual`` on stdin moves the pilot's switch."""
    if kind == "imu":
        bus = MockI2cBus(socket_path=socket_path)
        mpu_chip = bus.add(Mpu9250Chip(seed=3))
        bus.add(Ak8963Chip(parent=mpu_chip, seed=3))   # type: ignore[arg-type]
        bus.start()
        stop: Callable[[], None] = bus.stop
        receiver = None
    else:
        chip = MockGpioChip(socket_path=socket_path, release_level=None).start()
        receiver = RcReceiverMock(chip, lines=RC_LINES)
        mux = MuxMock(chip, receiver, enable_line=ENABLE, select_line=SELECT)
        receiver.set_mode_switch(False)
        receiver.start()
        mux.start()

        def stop() -> None:
            mux.stop()
            receiver.stop()  # type: ignore[union-attr]
            chip.stop()
    print("ready", flush=True)
    for line in sys.stdin:
        if receiver is not None and line.strip() in ("auto", "manual"):
            receiver.set_mode_switch(line.strip() == "auto")
        print("ok", flush=True)
    stop()
    return 0


class MockProcess:
    """The mocks of one driver in a child process (see :func:`serve_mocks`)."""

    def __init__(self, kind: str, socket_path: Path) -> None:
        self.proc = subprocess.Popen([sys.executable, __file__, "--serve", kind, str(socket_path)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None and self.proc.stdin is not None
        if self.proc.stdout.readline().strip() != "ready":
            raise RuntimeError(f"the {kind} mocks did not start")

    def say(self, command: str) -> None:
        """Send *command* and wait for its acknowledgement."""
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()
        self.proc.stdout.readline()

    def close(self) -> None:
        """End the child (stdin closed) and wait for it."""
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        self.proc.wait(timeout=10)


# ------------------------------------------------------------------ rc -------------------------------
def health(name: str, status: str = "ok", **details: str) -> t.Health:
    """A Health of *name* as the bus would hand it to a callback."""
    msg = t.Health()
    msg.header.source, msg.name, msg.status = name, name, status
    set_details(msg, details)
    return msg


def estimate(k: int) -> t.StateInformation:
    """A converged STATE_ESTIMATE whose sigmas move a little each time (as a filter's do)."""
    msg = t.StateInformation()
    msg.header.source, msg.sensor_name = "estimator", "estimator"
    s = 0.5 + 0.01 * (k % 7)
    msg.set(x=1.0, y=2.0, x_sigma=s, y_sigma=s, psi=0.3, psi_sigma=0.02)
    return msg


def feed_evidence(driver: Any, stop: threading.Event) -> None:
    """What the bus handler would call: Health of every watched service at 1 Hz, estimates at 20 Hz."""
    watched = sorted(driver.prearm.watched)
    extra = {"gps": {"data": "fresh", "fix_type": "3D", "h_sigma_m": "1.0", "satellites": "9"},
             "imu": {"calibrated": "True"},
             "estimator": {"position_sigma_m": "0.5", "heading_sigma_deg": "1.0"}}
    k = 0
    while not stop.wait(0.05):
        k += 1
        if driver.prearm.needs_estimate:
            driver._on_estimate(estimate(k))
        if k % 20 == 0 or k == 1:
            for name in watched:
                driver._on_health(health(name, **extra.get(name, {})))


def bench_rc(root: Path, *, seconds: float, profiled: bool) -> None:
    from u2sa_hw.drivers.rc_mux.driver import RcMuxDriver

    root.mkdir(parents=True)
    mocks = MockProcess("rc", root / "gpio.sock")
    profile = rover_profile(root / "rover", gpio_sock=root / "gpio.sock", i2c_sock=root / "i2c.sock")
    counts: dict[str, int] = {}
    driver = RcMuxDriver("rc", profile=profile, settings=profile.services["rc"].settings,
                         transport=Transport(private_lcm_url(), name="bench-rc"))
    driver.publish = capture_publish(counts)  # type: ignore[method-assign]
    driver.running = True
    stop = threading.Event()
    prof = cProfile.Profile() if profiled else None
    loop = threading.Thread(target=run_profiled(driver.run, prof), name="u2sa rc", daemon=True)
    feeder = threading.Thread(target=feed_evidence, args=(driver, stop), name="evidence", daemon=True)
    feeder.start()
    loop.start()
    try:
        time.sleep(2.0)                           # manual: the pilot arms
        mocks.say("auto")
        deadline = time.monotonic() + 10.0
        while not driver.enabled and time.monotonic() < deadline:
            time.sleep(0.05)
        print(f"rc: autonomy enabled: {driver.enabled} ({driver.autonomy_allowed()[1] or 'all conditions hold'})")
        time.sleep(0.5)
        reader = find_thread("gpio-mock-")
        edges0 = 2 * driver.meter.pulses
        cpu0, rd0, wall0, sent0 = thread_cpu_s(loop), thread_cpu_s(reader) if reader else 0.0, time.monotonic(), \
            dict(counts)
        time.sleep(seconds)
        cpu1, rd1, wall1 = thread_cpu_s(loop), thread_cpu_s(reader) if reader else 0.0, time.monotonic()
        edges = 2 * driver.meter.pulses - edges0
    finally:
        stop.set()
        driver.stop()
        loop.join(timeout=5)
        driver.gpio.close()
        mocks.close()
    wall = wall1 - wall0
    published = {c: n - sent0.get(c, 0) for c, n in counts.items()}
    print(f"rc: {edges} edges in {wall:.1f} s ({edges / wall:.0f}/s); published {published}")
    for what, cpu in (("loop thread", cpu1 - cpu0), ("port reader", rd1 - rd0)):
        print(f"rc: {what}   {1e6 * cpu / edges:7.1f} us/edge  {100 * cpu / wall:5.2f} % of a core")
    print_profile(prof, "the rc loop thread")


def bench_rc_recorded(root: Path, *, frames: int, profiled: bool) -> None:
    """Deterministic: *frames* recorded frames (and the Health and estimates the pre-arm checks read,
    handed over by the chip as a replay chip does) fed at once to the driver on a device-clock chip; the
    loop thread's CPU per edge. Without a select read-back (nothing here answers the enable line)."""
    from u2sa_hw.drivers.rc_mux.driver import RcMuxDriver
    from u2sa_hw import channels as ch

    root.mkdir(parents=True)
    chip = MockGpioChip(socket_path=str(root / "gpio.sock"), release_level=None, device_clock=True).start()
    for line in RC_LINES.values():
        chip.drive_input(line, 0)
    profile = rover_profile(root / "rover", gpio_sock=root / "gpio.sock", i2c_sock=root / "i2c.sock",
                            select_line=-1)
    counts: dict[str, int] = {}
    driver = RcMuxDriver("rc", profile=profile, settings=profile.services["rc"].settings,
                         transport=Transport(private_lcm_url(), name="bench-rc"))
    driver.publish = capture_publish(counts)  # type: ignore[method-assign]
    driver.running = True
    prof = cProfile.Profile() if profiled else None
    loop = threading.Thread(target=run_profiled(driver.run, prof), name="u2sa rc", daemon=True)
    loop.start()
    extra = {"gps": {"data": "fresh", "fix_type": "3D", "h_sigma_m": "1.0", "satellites": "9"},
             "imu": {"calibrated": "True"}}
    try:
        deadline = time.monotonic() + 10
        while not (chip.consumers() and driver._recorded_bus) and time.monotonic() < deadline:
            time.sleep(0.01)
        chip.set_origin(0)
        cpu0, edges, start = thread_cpu_s(loop), 0, 1_000_000_000
        for k in range(frames):
            frame = start + k * 20_000_000
            if k % 50 == 0:
                for name in sorted(driver.prearm.watched):
                    chip.bus(frame - 1_000_000, ch.HEALTH, health(name, **extra.get(name, {})).encode())
            if k % 5 in (0, 2) and ch.STATE_ESTIMATE in driver._recorded_bus:
                chip.bus(frame - 500_000, ch.STATE_ESTIMATE, estimate(k).encode())
            if k % 50 == 0:   # the chip drops what its client's queue cannot hold, as a kernel would
                while chip.backlog() > 200:
                    time.sleep(0.001)
            widths = {"throttle": 1600, "steering": 1500 + k % 5, "mode": 1000 if k < 100 else 2000}
            for slot, (name, line) in enumerate(RC_LINES.items()):
                rise = frame + slot * 6_666_666
                chip.drive_input(line, 1, rise)
                chip.drive_input(line, 0, rise + widths[name] * 1000)
                edges += 2
        last = start + frames * 20_000_000
        chip.tick(last)
        deadline = time.monotonic() + 60
        while (driver.clock_ns is None or driver.clock_ns < last) and time.monotonic() < deadline:
            time.sleep(0.01)
        if chip.dropped_edges:
            print(f"rc recorded: the chip dropped {chip.dropped_edges} frames: the figures are not comparable")
        cpu = thread_cpu_s(loop) - cpu0
        why = driver.autonomy_allowed()[1]
    finally:
        driver.stop()
        loop.join(timeout=5)
        driver.gpio.close()
        chip.stop()
    print(f"rc recorded: {frames} frames, {edges} edges; published {counts}; autonomy enabled at the end: "
          f"{driver.enabled} ({why or 'all conditions hold'})")
    print(f"rc recorded: loop thread {1e6 * cpu / edges:6.1f} us/edge (at 300 edges/s: "
          f"{300 * 100 * cpu / edges:4.2f} % of a core)")
    print_profile(prof, "the rc loop thread (recorded input)")


# ------------------------------------------------------------------ imu ------------------------------
def bench_imu(root: Path, *, seconds: float, samples: int, profiled: bool) -> None:
    from u2sa_hw.drivers.imu.mpu9250 import Mpu9250ImuDriver

    root.mkdir(parents=True)
    mocks = MockProcess("imu", root / "i2c.sock")
    profile = rover_profile(root / "rover", gpio_sock=root / "gpio.sock", i2c_sock=root / "i2c.sock")
    counts: dict[str, int] = {}
    driver = Mpu9250ImuDriver("imu", profile=profile, settings=profile.services["imu"].settings,
                              transport=Transport(private_lcm_url(), name="bench-imu"))
    driver.publish = capture_publish(counts)  # type: ignore[method-assign]
    driver.publish_health = lambda: None      # type: ignore[method-assign]
    try:
        driver.setup()
        driver.sample_once()                      # opens and sets up the chip (not measured)
        prof = cProfile.Profile() if profiled else None
        before, cpu0 = driver.samples, time.thread_time()
        run_profiled(lambda: [driver.sample_once() for _ in range(samples)], prof)()
        cpu = time.thread_time() - cpu0
        done = driver.samples - before
        print(f"imu: back to back: {done} samples, {1e6 * cpu / done:6.1f} us/sample (driver thread); "
              f"magnetometer {driver.mag.state if driver.mag else 'none'}")
        print_profile(prof, "imu sample_once")
        driver.running = True
        loop = threading.Thread(target=driver.run, name="u2sa imu", daemon=True)
        loop.start()
        time.sleep(1.0)
        s0, c0, w0 = driver.samples, thread_cpu_s(loop), time.monotonic()
        time.sleep(seconds)
        s1, c1, w1 = driver.samples, thread_cpu_s(loop), time.monotonic()
        driver.stop()
        loop.join(timeout=5)
        wall, n = w1 - w0, s1 - s0
        print(f"imu: live at {float(driver.config['rate_hz']):g} Hz: {n} samples in {wall:.1f} s; loop thread "
              f"{1e6 * (c1 - c0) / n:6.1f} us/sample  {100 * (c1 - c0) / wall:5.2f} % of a core")
    finally:
        driver.port.close()
        if driver.mag is not None:
            driver.mag.close()
        mocks.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", choices=("rc", "imu"))
    parser.add_argument("--seconds", type=float, default=20.0, help="the live window of each driver")
    parser.add_argument("--samples", type=int, default=2000, help="IMU samples read back to back")
    parser.add_argument("--frames", type=int, default=1500, help="RC frames fed at once (recorded input)")
    parser.add_argument("--profile", action="store_true", help="print a cProfile of the measured loop")
    parser.add_argument("--serve", nargs=2, metavar=("KIND", "SOCKET"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve:
        return serve_mocks(*args.serve)
    use_run_key()   # without an installed key, a fresh one for this run
    root = Path(tempfile.mkdtemp(prefix="u2sa-dlc-", dir="/tmp"))   # short: Unix socket paths are limited
    try:
        if args.only in (None, "rc"):
            bench_rc_recorded(root / "rc-recorded", frames=args.frames, profiled=args.profile)
            bench_rc(root / "rc", seconds=args.seconds, profiled=args.profile)
        if args.only in (None, "imu"):
            bench_imu(root / "imu", seconds=args.seconds, samples=args.samples, profiled=args.profile)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
