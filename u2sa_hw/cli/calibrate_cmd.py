"""``u2sa calibrate compass|imu SERVICE``: collect raw vectors from a running service, fit, check, save.

The command turns the service's calibration stream on (``calibration_stream_s`` over the
signed bus; the service then publishes raw, uncorrected vectors on ``CAL.<service>`` and
stops by itself when that time runs out), shows coverage as the operator turns the
vehicle, and turns the stream off again at the end, on Ctrl-C and on any error. The fit
(u2sa_hw.calibration) is checked; a bad result is refused with the reason and nothing is
saved. A good one is saved through the normal config change (checked by the service,
written atomically, applied live), offset last. See docs/calibration.md.
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from typing import Any, Callable, Mapping, TextIO

import numpy as np

from u2sa_hw import lcmtypes as t
from u2sa_hw.calibration import accelerometer as acc
from u2sa_hw.calibration import magnetometer as magcal
from u2sa_hw.cli.common import add_vehicle_option, bus_client, no_answer_error

CAL_PREFIX = "CAL."
STREAM_MARGIN_S = 30.0      # the service streams this much longer than --timeout, then stops by itself
FIRST_SAMPLE_S = 5.0        # no CAL sample within this: the service has no such sensor working
KINDS = {
    # kind: (config fields the service must have, what to tell when it has not)
    "compass": (("mag_offset", "mag_matrix", "calibration_stream_s"),
                "has no magnetometer calibration (a serial compass offers it only with format = \"os5000\" "
                "and the Mx/My/Mz outputs enabled; an NMEA compass calibrates itself, see its manual)"),
    "imu": (("accel_offset", "accel_matrix", "calibration_stream_s"),
            "has no accelerometer calibration (the MPU-6050/6500/9250 driver has; the BNO055 calibrates itself)"),
}

DESCRIPTION = """\
Calibrate a running service's sensor and save the result to its config.

compass: hard and soft iron of a magnetometer (MPU-9250's AK8963, or an OS5000 that
  reports raw field values). Turn the vehicle slowly through every orientation: all
  headings, and rolled and pitched both ways (on its side, nose up and down) -- a level
  turn alone leaves the vertical unknown and is refused. Coverage is the share of 26
  directions the field has been seen from; collection ends when all are seen or at
  --timeout. Keep away from steel and running motors.
imu: accelerometer offsets and scales from six still poses: hold the vehicle (or the
  board) still for a second with each axis up and then down (+x -x +y -y +z -z).

Calibrate imu first: the heading is levelled with the accelerometer's tilt.
The result is refused, and nothing saved, when the fit's residual or the coverage is
bad; otherwise it is checked and saved by the service (atomic write, applied at once).
Ctrl-C stops without saving; the service's raw stream is turned off in every case.
Procedure and numbers: docs/calibration.md.
"""

EPILOG = """\
examples:
  u2sa calibrate compass imu                 turn the vehicle until coverage is full
  u2sa calibrate compass imu --dry-run       fit and show, save nothing
  u2sa calibrate imu imu --timeout 180       six poses, three minutes to do them
  u2sa calibrate compass compass             an OS5000 with raw_field = true (Mx/My/Mz on)
  u2sa param list imu                        mag_offset/mag_matrix, accel_offset/accel_matrix
"""


def register(sub: Any) -> None:
    """Add the ``calibrate`` subcommand."""
    p = sub.add_parser("calibrate", help="calibrate a magnetometer (compass) or accelerometer (imu) and save it",
                       description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("kind", choices=sorted(KINDS), help="compass: magnetometer hard/soft iron; imu: accelerometer")
    p.add_argument("service", help="the running service (u2sa services lists them)")
    p.add_argument("--timeout", type=float, default=120.0, metavar="S",
                   help="seconds to collect before fitting what was collected (default 120)")
    p.add_argument("--min-coverage", type=float, default=magcal.MIN_COVERAGE, metavar="SHARE",
                   help=f"compass: least share of directions seen for a result to be saved "
                        f"(0..1, default {magcal.MIN_COVERAGE:g})")
    p.add_argument("--dry-run", action="store_true", help="fit and show the result, do not save it")
    p.add_argument("--bus-timeout", type=float, default=3.0, metavar="S",
                   help="seconds to wait for the service's answers (default 3)")
    add_vehicle_option(p)
    p.set_defaults(func=cmd_calibrate)


class Progress:
    """One status line: rewritten in place on a terminal, a plain line on a change otherwise."""

    def __init__(self, out: TextIO) -> None:
        self.out = out
        self.tty = out.isatty()
        self._last = ""

    def show(self, text: str) -> None:
        """Show *text* (only when it changed on a non-terminal)."""
        if self.tty:
            self.out.write("\r\033[K" + text)
            self.out.flush()
        elif text != self._last:
            print(text, file=self.out, flush=True)
        self._last = text

    def done(self) -> None:
        """End the in-place line."""
        if self.tty and self._last:
            self.out.write("\n")
            self.out.flush()


class MagCollector:
    """Raw field vectors, and the share of direction bins seen about a running centre."""

    def __init__(self) -> None:
        self.samples: list[tuple[float, float, float]] = []

    def add(self, msg: t.StateInformation) -> None:
        """Take a CAL message's field (x, y, z), when it has one."""
        if msg.has("x") and msg.has("y") and msg.has("z") and all(map(math.isfinite, (msg.x, msg.y, msg.z))):
            self.samples.append((msg.x, msg.y, msg.z))

    def coverage(self) -> float:
        """Share of the 26 direction bins seen (about the middle of the readings' range)."""
        if len(self.samples) < 2:
            return 0.0
        m = np.asarray(self.samples)
        centre = (m.max(axis=0) + m.min(axis=0)) / 2
        return magcal.coverage(m - centre)

    @property
    def count(self) -> int:
        """Field vectors received."""
        return len(self.samples)

    def finished(self) -> bool:
        """Every direction seen, with enough samples to fit."""
        return len(self.samples) >= magcal.MIN_SAMPLES and self.coverage() >= 1.0

    def status(self) -> str:
        """The progress line."""
        cov = self.coverage()
        bar = "#" * round(cov * 26) + "." * (26 - round(cov * 26))
        return f"coverage [{bar}] {cov:4.0%}  samples {len(self.samples)}"


class AccelCollector:
    """The six poses as they are captured."""

    def __init__(self) -> None:
        self.poses = acc.PoseCollector()
        self.samples = 0

    def add(self, msg: t.StateInformation) -> None:
        """Take a CAL message's specific force (x_ddot, y_ddot, z_ddot)."""
        if msg.has("x_ddot") and msg.has("y_ddot") and msg.has("z_ddot"):
            self.samples += 1
            self.poses.add((msg.x_ddot, msg.y_ddot, msg.z_ddot))

    @property
    def count(self) -> int:
        """Specific-force vectors received."""
        return self.samples

    def finished(self) -> bool:
        """All six poses captured."""
        return not self.poses.missing

    def status(self) -> str:
        """The progress line: captured poses in brackets."""
        marks = " ".join(f"[{p}]" if p in self.poses.means else f" {p} " for p in acc.POSES)
        return f"poses {marks}  ({6 - len(self.poses.missing)}/6; hold each still about a second)"


def _set(bus: Any, args: Any, name: str, value: str) -> None:
    from u2sa_hw.cli import CliError

    resp = bus.set_config(args.service, name, value, timeout=args.bus_timeout)
    if resp is None:
        raise no_answer_error(args, f"service '{args.service}' did not answer setting {name}")
    if not resp.ok:
        raise CliError(f"{args.service} refused {name}: {resp.error}")


def _list_text(values: list[float]) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


def _collect(bus: Any, args: Any, collector: Any, progress: Progress) -> None:
    """Stream CAL.<service> into *collector* until it is finished, --timeout, or Ctrl-C (raised)."""
    from u2sa_hw.cli import CliError

    lock = threading.Lock()

    def on_cal(_channel: str, msg: t.StateInformation) -> None:
        with lock:
            collector.add(msg)

    sub = bus.transport.subscribe(CAL_PREFIX + args.service, t.StateInformation, on_cal)
    try:
        _set(bus, args, "calibration_stream_s", repr(float(args.timeout + STREAM_MARGIN_S)))
        start = time.monotonic()
        while True:
            time.sleep(0.2)
            with lock:
                progress.show(collector.status())
                if collector.finished():
                    return
                count = collector.count
            elapsed = time.monotonic() - start
            if count == 0 and elapsed > FIRST_SAMPLE_S:
                what = "magnetometer" if isinstance(collector, MagCollector) else "accelerometer"
                raise CliError(f"{args.service} sends no {what} samples on {CAL_PREFIX}{args.service} within "
                               f"{FIRST_SAMPLE_S:g} s (no {what} on this chip, or it is not answering: "
                               f"u2sa health {args.service}); nothing saved")
            if elapsed > args.timeout:
                return
    finally:
        progress.done()
        bus.transport.unsubscribe(sub)
        _stream_off(bus, args)


def _stream_off(bus: Any, args: Any) -> None:
    resp = bus.set_config(args.service, "calibration_stream_s", "0.0", timeout=args.bus_timeout)
    if resp is None or not resp.ok:
        print(f"u2sa: warning: could not turn {args.service}'s calibration stream off "
              f"({'no answer' if resp is None else resp.error}); it stops by itself within "
              f"{args.timeout + STREAM_MARGIN_S:g} s", file=sys.stderr)


EARTH_FIELD = {"uT": "25..65", "mG": "250..650"}   # the Earth's field strength in each unit


def mag_unit(config: Mapping[str, str]) -> str:
    """The unit of the raw field a service streams on CAL.<service>: ``mG`` for a serial compass (an
    OS5000's Mx/My/Mz; its service has ``raw_field``), ``uT`` for the MPU-9250's AK8963."""
    return "mG" if "raw_field" in config else "uT"


def _fit_compass(collector: MagCollector, args: Any,
                 config: Mapping[str, str]) -> tuple[dict[str, list[float]], list[str], list[str]]:
    result = magcal.fit_ellipsoid(collector.samples)
    m, unit = result.matrix, mag_unit(config)
    lines = [f"offset (hard iron)   {', '.join(f'{v:.2f}' for v in result.offset)} {unit}",
             *(f"matrix (soft iron)   {'  '.join(f'{v:8.4f}' for v in row)}" for row in m),
             f"field strength       {result.field_strength:.1f} {unit} (Earth: {EARTH_FIELD[unit]})",
             f"residual             {result.residual:.4f} (at most {magcal.MAX_RESIDUAL})",
             f"coverage             {result.coverage:.0%} (at least {args.min_coverage:.0%})",
             f"samples              {result.samples}"]
    return result.as_config(), result.problems(min_coverage=args.min_coverage), lines


def _fit_imu(collector: AccelCollector, _args: Any,
             _config: Mapping[str, str]) -> tuple[dict[str, list[float]], list[str], list[str]]:
    result = acc.fit_six_pose(collector.poses.means)
    lines = [f"offset               {', '.join(f'{v:.4f}' for v in result.offset)} m/s^2",
             *(f"matrix               {'  '.join(f'{v:8.5f}' for v in row)}" for row in result.matrix),
             f"residual             {result.residual:.4f} m/s^2 (at most {acc.MAX_RESIDUAL})"]
    return result.as_config(), result.problems(), lines


FITS: dict[str, tuple[Callable[[], Any], Callable[..., Any]]] = {
    "compass": (MagCollector, _fit_compass),
    "imu": (AccelCollector, _fit_imu),
}


def cmd_calibrate(args: Any) -> int:
    """Run one calibration (see the module docstring)."""
    from u2sa_hw.cli import CliError

    if not 0.0 < args.min_coverage <= 1.0:
        raise CliError(f"--min-coverage must be within 0..1 (a share of directions), got {args.min_coverage:g}")
    if not args.timeout > 0:
        raise CliError(f"--timeout must be > 0 s, got {args.timeout:g}")
    needed, missing_text = KINDS[args.kind]
    make_collector, fit = FITS[args.kind]
    with bus_client(args) as bus:
        resp = bus.get_config(args.service, timeout=args.bus_timeout)
        if resp is None:
            raise no_answer_error(args, f"service '{args.service}' did not answer within {args.bus_timeout:g} s "
                                  "(u2sa services lists the live ones)")
        config = {f.name: f.value for f in resp.fields}
        if not all(n in config for n in needed):
            raise CliError(f"{args.service} {missing_text}")
        if args.kind == "compass" and "raw_field" in config and (
                config["raw_field"] != "true" or config.get("format", "").strip("\"'").lower() != "os5000"):
            raise CliError(f"{args.service} reports no raw field values to calibrate: calibration needs "
                           f'format = "os5000" with the compass\'s Mx/My/Mz outputs enabled and raw_field = true '
                           f"(now format = {config.get('format', '?')}, raw_field = {config['raw_field']}); "
                           "otherwise use the compass's own calibration (see its manual)")
        collector = make_collector()
        print(f"calibrating {args.kind} of {args.service}: "
              + ("turn the vehicle through every orientation" if args.kind == "compass"
                 else "hold it still with each axis up, then down") + f" (up to {args.timeout:g} s, Ctrl-C stops)")
        try:
            _collect(bus, args, collector, Progress(sys.stdout))
        except KeyboardInterrupt:
            raise CliError("interrupted: nothing saved", code=130) from None
        try:
            values, problems, lines = fit(collector, args, config)
        except (magcal.CalibrationError, acc.CalibrationError) as exc:
            raise CliError(f"{args.service}: no calibration: {exc}; nothing saved") from None
        print("\n".join(lines))
        if problems:
            raise CliError(f"{args.service}: calibration refused, nothing saved: " + "; ".join(problems))
        if args.dry_run:
            print("dry run: not saved")
            return 0
        # the matrix first, the offset last: a half-applied result is at worst the old offset with the new matrix
        for name in sorted(values, key=lambda n: n.endswith("_offset")):
            _set(bus, args, name, _list_text(values[name]))
        print(f"saved to {args.service}'s config and applied ({', '.join(sorted(values))}); "
              f"u2sa param list {args.service} shows them")
    return 0
