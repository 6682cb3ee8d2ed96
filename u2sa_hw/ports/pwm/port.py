"""PWM channels: Linux PWM sysfs (``/sys/class/pwm/pwmchip0``), a sysfs-shaped directory
(the mock the simulation reads), or a PCA9685 on I2C (``pca9685:<bus>:<addr>``, handled by
``u2sa_hw.ports.pwm.pca9685``, imported only when such an address is opened).

Sysfs semantics, as the kernel documents them (Documentation/driver-api/pwm.rst):
writing channel N to ``<chip>/export`` creates ``<chip>/pwmN/`` with ``period``,
``duty_cycle`` (decimal ns), ``enable`` ("1"/"0") and ``polarity``; ``duty_cycle`` may
never exceed ``period`` (so the period is written first when it grows, the duty first
when it shrinks); ``unexport`` removes the channel again.

A directory outside ``/sys`` is a mock chip. No kernel answers there, so the backend plays
the kernel's part: export creates ``pwmN/`` and its files, unexport removes them, and a
write that breaks the rules above fails with EINVAL as the kernel's would. Mock files are
replaced atomically (temp file + rename) because the simulation reads them concurrently;
real sysfs attributes are written in place, which is the only way they can be written.
``make_sysfs_pwm_tree`` creates such a chip directory.

Every change (period, duty, enable) is tapped as a ``RawPwmWrite``.
"""

from __future__ import annotations

import errno
import logging
import os
import shutil
import time
from pathlib import Path
from typing import Protocol, runtime_checkable

from u2sa_hw.messages import RawPwmWrite
from u2sa_hw.ports.errors import PortClosed, PortIOError, PortUnavailable
from u2sa_hw.ports.tap import Tap, call_tap, tapping

log = logging.getLogger(__name__)

PCA9685_PREFIX = "pca9685:"
EXPORT_WAIT = 2.0  # s; udev may still be chgrp-ing a freshly exported channel's files
PWM_PERMISSION_FIX = ("give group 'gpio' write access to the chip with udev/60-u2sa-permissions.rules "
                      "(u2sa install) and run the service in that group, or run it as root")


@runtime_checkable
class PwmChannel(Protocol):
    """One PWM output, whatever drives it (sysfs chip, PCA9685)."""

    device: str
    address: str
    channel: int

    def set_pulse_ns(self, ns: int) -> None:
        """Set the high time of each period, in nanoseconds."""

    def set_pulse_us(self, us: float) -> None:
        """Set the high time of each period, in microseconds (servos: 1000-2000)."""

    def enable(self, on: bool) -> None:
        """Start or stop the output."""

    def close(self) -> None:
        """Stop the output and release the channel."""


def tap_pwm_state(tap: Tap | None, *, device: str, channel: int, period_ns: int, duty_ns: int,
                  enabled: bool) -> None:
    """Hand *tap* the output's state after a write, as one ``RawPwmWrite`` (built only while it taps)."""
    if not tapping(tap):
        return
    record = RawPwmWrite()
    record.device = device
    record.channel = channel
    record.period_ns = period_ns
    record.duty_ns = duty_ns
    record.enabled = enabled
    call_tap(tap, record)


def is_real_sysfs(path: str | os.PathLike[str]) -> bool:
    """True if *path* lies in the kernel's sysfs (so the kernel, not we, manages it)."""
    return os.path.realpath(path).startswith("/sys/")


def make_sysfs_pwm_tree(path: str | os.PathLike[str], *, npwm: int = 16) -> Path:
    """Create a sysfs-shaped PWM chip directory at *path* (``npwm``, ``export``,
    ``unexport``) for tests and the simulation; returns its path."""
    chip = Path(path)
    chip.mkdir(parents=True, exist_ok=True)
    (chip / "npwm").write_text(f"{npwm}\n")
    for name in ("export", "unexport"):
        (chip / name).touch()
    return chip


class SysfsPwmChannel:
    """One channel of a sysfs PWM chip (real or mock); see the module docstring."""

    def __init__(self, *, device: str, chip: Path, channel: int, tap: Tap | None = None) -> None:
        self.device = device
        self.address = str(chip)
        self.channel = channel
        self.chip = chip
        self.path = chip / f"pwm{channel}"
        self.mock = not is_real_sysfs(chip)
        self._tap = tap
        self._closed = False
        self.period_ns = self._read_int("period")
        self.duty_ns = self._read_int("duty_cycle")
        self.enabled = self._read_int("enable") == 1

    # -- file access -------------------------------------------------------------------
    def _read_int(self, name: str) -> int:
        try:
            text = (self.path / name).read_text().strip()
        except OSError as exc:
            raise self._error(exc, f"reading {self.path / name}") from exc
        try:
            return int(text or "0")
        except ValueError:
            raise PortIOError(self.device, f"{self.path / name} holds {text!r}, not a number",
                              address=self.address, fix="unexport and export the channel again") from None

    def _write(self, name: str, value: int) -> None:
        """Write one attribute as the kernel expects (decimal, no padding)."""
        if self._closed:
            raise PortClosed(self.device, "channel is closed", address=self.address,
                             fix="open the channel again (ReconnectingPort does this)")
        path = self.path / name
        try:
            if self.mock:
                self._mock_check(name, value)
                _replace_file(path, f"{value}\n")
            else:
                fd = os.open(path, os.O_WRONLY)
                try:
                    os.write(fd, str(value).encode())
                finally:
                    os.close(fd)
        except OSError as exc:
            raise self._error(exc, f"writing {value} to {path}") from exc

    def _mock_check(self, name: str, value: int) -> None:
        """Refuse what the kernel refuses (the mock has no kernel behind it)."""
        if not self.path.is_dir():
            raise FileNotFoundError(errno.ENOENT, "channel directory is gone", str(self.path))
        if name == "duty_cycle" and value > self._read_int("period"):
            raise OSError(errno.EINVAL, f"duty_cycle {value} > period", str(self.path / name))
        if name == "period" and value < self._read_int("duty_cycle"):
            raise OSError(errno.EINVAL, f"period {value} < duty_cycle", str(self.path / name))
        if name == "enable" and value == 1 and self._read_int("period") == 0:
            raise OSError(errno.EINVAL, "enable with period 0", str(self.path / name))

    def _error(self, exc: OSError, action: str) -> PortClosed | PortIOError | PortUnavailable:
        if exc.errno in (errno.ENOENT, errno.ENODEV, errno.ENXIO):
            self._closed = True
            return PortClosed(self.device, f"{action}: PWM chip gone ({exc})", address=self.address,
                              fix="check the PWM chip driver / overlay (or restart the mock); ReconnectingPort reopens it")
        if exc.errno in (errno.EACCES, errno.EPERM):
            return PortUnavailable(self.device, f"{action}: no permission ({exc})", address=self.address,
                                   fix=PWM_PERMISSION_FIX)
        return PortIOError(self.device, f"{action} failed ({exc})", address=self.address,
                           fix="period must be > 0 and duty_cycle <= period; check the chip supports the period")

    # -- PwmChannel --------------------------------------------------------------------
    def _tap_state(self) -> None:
        tap_pwm_state(self._tap, device=self.device, channel=self.channel, period_ns=self.period_ns,
                      duty_ns=self.duty_ns, enabled=self.enabled)

    def configure(self, *, period_ns: int, duty_ns: int) -> None:
        """Set period and duty together, in the order that keeps duty <= period throughout."""
        if period_ns <= 0 or not 0 <= duty_ns <= period_ns:
            raise ValueError(f"{self.device}: need 0 <= duty ({duty_ns}) <= period ({period_ns}), period > 0")
        if (period_ns, duty_ns) == (self.period_ns, self.duty_ns):
            return
        if period_ns >= self.period_ns:
            self._write("period", period_ns)
            self.period_ns = period_ns
            self._write("duty_cycle", duty_ns)
        else:
            self._write("duty_cycle", duty_ns)
            self.duty_ns = duty_ns
            self._write("period", period_ns)
        self.period_ns, self.duty_ns = period_ns, duty_ns
        self._tap_state()

    def set_period_ns(self, ns: int) -> None:
        """Change the period, shortening the duty if it would no longer fit."""
        self.configure(period_ns=ns, duty_ns=min(self.duty_ns, ns))

    def set_pulse_ns(self, ns: int) -> None:
        """Set the duty (high time) in ns; ValueError if it is negative or exceeds the period."""
        ns = int(ns)
        if not 0 <= ns <= self.period_ns:
            raise ValueError(f"{self.device}: pulse {ns} ns outside 0..{self.period_ns} ns (the period)")
        if ns != self.duty_ns:
            self._write("duty_cycle", ns)
            self.duty_ns = ns
            self._tap_state()

    def set_pulse_us(self, us: float) -> None:
        """Set the duty (high time) in microseconds."""
        self.set_pulse_ns(round(us * 1000))

    def enable(self, on: bool) -> None:
        """Start (``"1"``) or stop (``"0"``) the output."""
        on = bool(on)
        if on != self.enabled:
            self._write("enable", 1 if on else 0)
            self.enabled = on
            self._tap_state()

    def close(self) -> None:
        """Stop the output and unexport the channel (idempotent; a vanished chip is fine)."""
        if self._closed:
            return
        try:
            self.enable(False)
        except (PortClosed, PortIOError) as exc:
            log.debug("%s: disabling on close: %s", self.device, exc)
        self._closed = True
        try:
            _write_control(self.chip / "unexport", self.channel)
            if self.mock:
                shutil.rmtree(self.path, ignore_errors=True)
        except OSError as exc:
            log.debug("%s: unexport on close: %s", self.device, exc)

    def __repr__(self) -> str:
        return f"<SysfsPwmChannel {self.device} {self.path} period={self.period_ns} duty={self.duty_ns}>"


def _replace_file(path: Path, text: str) -> None:
    """Replace *path*'s content atomically (mock files only; sysfs cannot be renamed)."""
    if not path.parent.is_dir():
        raise FileNotFoundError(errno.ENOENT, "No such file or directory", str(path))
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _write_control(path: Path, channel: int) -> None:
    """Write a channel number to a chip's export/unexport file."""
    fd = os.open(path, os.O_WRONLY | (0 if is_real_sysfs(path) else os.O_TRUNC))
    try:
        os.write(fd, str(channel).encode())
    finally:
        os.close(fd)


def _export(*, device: str, chip: Path, channel: int) -> Path:
    """Make ``<chip>/pwm<channel>`` exist: the kernel creates it on export, for a mock we do."""
    path = chip / f"pwm{channel}"
    if path.is_dir():
        return path
    try:
        _write_control(chip / "export", channel)
    except OSError as exc:
        fix = (PWM_PERMISSION_FIX
               if exc.errno in (errno.EACCES, errno.EPERM) else "check the channel number and that nothing else uses it")
        raise PortUnavailable(device, f"cannot export channel {channel} ({exc})", address=str(chip), fix=fix) from exc
    if not is_real_sysfs(chip):
        path.mkdir()
        for name, text in (("period", "0"), ("duty_cycle", "0"), ("enable", "0"), ("polarity", "normal")):
            (path / name).write_text(text + "\n")
        return path
    deadline = time.monotonic() + EXPORT_WAIT
    while not os.access(path / "duty_cycle", os.W_OK):
        if time.monotonic() > deadline:
            raise PortUnavailable(device, f"exported channel {channel} but {path} is not writable",
                                  address=str(chip), fix=PWM_PERMISSION_FIX)
        time.sleep(0.01)  # the kernel (and udev's chgrp) finish asynchronously
    return path


def open_sysfs_pwm(*, device: str, address: str, channel: int, period_ns: int = 20_000_000,
                   tap: Tap | None = None) -> SysfsPwmChannel:
    """Open *channel* of the sysfs chip directory *address* (real under /sys, else a mock tree) and set its
    period; a freshly exported channel is disabled until ``enable(True)``."""
    if period_ns <= 0:
        raise ValueError(f"{device}: period_ns must be > 0, got {period_ns}")
    chip = Path(address)
    if not (chip / "export").exists():
        fix = ("enable the PWM controller (e.g. dtoverlay=pwm-2chan on a Raspberry Pi) and check ls /sys/class/pwm"
               if is_real_sysfs(address) else
               "start the mock PWM device (or create the tree with make_sysfs_pwm_tree), or fix the address")
        raise PortUnavailable(device, "no PWM chip here (no export file)", address=address, fix=fix)
    try:
        npwm = int((chip / "npwm").read_text().strip())
    except (OSError, ValueError):
        npwm = None
    if channel < 0 or (npwm is not None and channel >= npwm):
        raise PortUnavailable(device, f"channel {channel} does not exist (chip has {npwm} channels)",
                              address=address, fix=f"use a channel 0..{(npwm or 1) - 1} in the device's address")
    _export(device=device, chip=chip, channel=channel)
    pwm = SysfsPwmChannel(device=device, chip=chip, channel=channel, tap=tap)
    pwm.configure(period_ns=period_ns, duty_ns=min(pwm.duty_ns, period_ns))
    return pwm


def open_pwm(*, device: str, address: str, channel: int, period_ns: int = 20_000_000,
             tap: Tap | None = None) -> PwmChannel:
    """Open PWM *channel* of the chip at *address* and set its period (a freshly exported
    channel is disabled until ``enable(True)``); ``pca9685:...`` addresses go to the
    PCA9685 backend. Raises PortUnavailable naming the chip and the fix."""
    if period_ns <= 0:
        raise ValueError(f"{device}: period_ns must be > 0, got {period_ns}")
    if address.startswith(PCA9685_PREFIX):
        from u2sa_hw.ports.pwm.pca9685 import open_pca9685_pwm

        return open_pca9685_pwm(device=device, address=address, channel=channel, period_ns=period_ns, tap=tap)
    return open_sysfs_pwm(device=device, address=address, channel=channel, period_ns=period_ns, tap=tap)
