"""A Linux sysfs PWM chip as a directory tree, and what the simulation reads back from it.

``SysfsPwmChip(path=..., npwm=4)`` makes ``path`` look like ``/sys/class/pwm/pwmchipN``
(``npwm``, ``export``, ``unexport``; the tree maker is
:func:`u2sa_hw.ports.pwm.port.make_sysfs_pwm_tree`). A driver opens it by that path with
``open_pwm`` exactly as it opens the kernel's chip: exporting a channel creates ``pwmN/``
with ``period``, ``duty_cycle`` and ``enable`` (the port plays the kernel's part for a
directory outside ``/sys``, see docs/ports.md). The chip side reads those files, the way
the simulation reads a servo's pulse: ``pulse_width_us(channel)`` (0 while the channel is
disabled or not exported, as on the PCA9685 model), ``frame_period_us(channel)``,
``channel_state(channel)``. Reads are safe while the driver writes: the port replaces the
files atomically.

Faults: ``unbind()`` removes the whole tree (the chip's kernel driver unbound, an overlay
removed): the driver's next write fails with "PWM chip gone" and reopening fails until
``bind()`` creates an empty chip again (no channel exported, as after a reboot).
"""

from __future__ import annotations

import shutil
import threading
from pathlib import Path

from u2sa_hw.ports.pwm.port import make_sysfs_pwm_tree


class SysfsPwmChip:
    """A sysfs-shaped PWM chip with *npwm* channels at *path* (see the module docstring)."""

    def __init__(self, *, path: str | Path, npwm: int = 16, name: str = "pwmchip") -> None:
        if not 1 <= npwm <= 1024:
            raise ValueError(f"{name}: npwm must be 1..1024, got {npwm!r}")
        self.path = Path(path)
        self.npwm = int(npwm)
        self.name = name
        self._lock = threading.Lock()
        self._bound = False

    @property
    def address(self) -> str:
        """What a pwm_servo channel's ``address`` names: the chip directory."""
        return str(self.path)

    @property
    def bound(self) -> bool:
        """True between start()/bind() and stop()/unbind()."""
        return self._bound

    # ---- lifecycle and faults ----------------------------------------------------------------
    def start(self) -> "SysfsPwmChip":
        """Create the chip (an empty one: stale channels of an earlier run are removed)."""
        self.bind()
        return self

    def stop(self) -> None:
        """Remove the tree."""
        self.unbind()

    def bind(self) -> None:
        """Fault end / start: the chip appears, no channel exported."""
        with self._lock:
            if self.path.exists():
                shutil.rmtree(self.path)
            make_sysfs_pwm_tree(self.path, npwm=self.npwm)
            self._bound = True

    def unbind(self) -> None:
        """Fault: the chip disappears with every channel (its kernel driver was unbound)."""
        with self._lock:
            shutil.rmtree(self.path, ignore_errors=True)
            self._bound = False

    # ---- what the simulation reads -------------------------------------------------------------
    def exported(self) -> list[int]:
        """The channels a driver has exported, in order."""
        found = []
        for entry in self.path.glob("pwm[0-9]*"):
            suffix = entry.name[3:]
            if entry.is_dir() and suffix.isdigit():
                found.append(int(suffix))
        return sorted(found)

    def channel_state(self, channel: int) -> tuple[int, int, bool] | None:
        """(period ns, duty ns, enabled) of *channel* as its files say; None when not exported (or unreadable)."""
        self._check(channel)
        base = self.path / f"pwm{channel}"
        try:
            period = int((base / "period").read_text().strip() or "0")
            duty = int((base / "duty_cycle").read_text().strip() or "0")
            enabled = (base / "enable").read_text().strip() == "1"
        except (OSError, ValueError):
            return None
        return period, duty, enabled

    def pulse_width_us(self, channel: int) -> float:
        """The high time per frame the output produces, in µs (0 while disabled or not exported)."""
        state = self.channel_state(channel)
        if state is None or not state[2]:
            return 0.0
        return state[1] / 1000.0

    def frame_period_us(self, channel: int) -> float:
        """The frame period of *channel* in µs (0 while not exported)."""
        state = self.channel_state(channel)
        return 0.0 if state is None else state[0] / 1000.0

    def pulse_widths_us(self) -> list[float]:
        """:meth:`pulse_width_us` of every channel 0..npwm-1."""
        return [self.pulse_width_us(n) for n in range(self.npwm)]

    def _check(self, channel: int) -> None:
        if not 0 <= channel < self.npwm:
            raise ValueError(f"{self.name}: channel {channel} out of range 0..{self.npwm - 1}")

    def __repr__(self) -> str:
        return f"<SysfsPwmChip {self.path} npwm={self.npwm} {'bound' if self._bound else 'unbound'}>"
