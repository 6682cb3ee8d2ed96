"""Replay devices for PWM outputs: present for a servo driver whose input is the bus.

A PWM output's input is not on the device at all: the driver is commanded over the
bus (``ACTUATOR_CMD``, ``FAILSAFE``), and the replay republishes the recorded commands
(hil/replay.py). The device only has to be there: every output's device address is pointed
at a sysfs-shaped directory (``make_sysfs_pwm_tree``) or, for a PCA9685, at a mock PCA9685
on a mock I2C bus (from the recorded address alone), so the same port code runs and taps
the same ``RawPwmWrite`` records, which ``--compare`` compares with the recorded ones.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from u2sa_hw.ports.address import DeviceAddress, make_address

from u2sa_hw.hil.replay_plan import ReplayError


class PwmReplayRig:
    """The mock PWM outputs of one servo service: one sysfs-shaped tree per recorded sysfs chip,
    one mock I2C bus with a mock PCA9685 per recorded PCA9685 bus. Shared by the service's devices."""

    def __init__(self, *, service: str, run_dir: Path) -> None:
        self.service = service
        self.run_dir = run_dir
        self._trees: dict[str, tuple[Path, int]] = {}          # recorded chip directory -> (mock tree, channels)
        self._buses: dict[str, tuple[Path, set[int]]] = {}     # recorded bus -> (socket, chip addresses)
        self._objects: list[Any] = []
        self._started = False

    def add(self, device: str, real: DeviceAddress | None) -> str:
        """The replay address of output *device*, recorded at *real* (a pwm:// or pca9685:// address)."""
        if real is None or real.kind not in ("pwm", "pca9685"):
            raise ReplayError(f"service '{self.service}': output '{device}' has no PWM address in the log's profile "
                              f"({real.url if real else 'none'}); give the profile with --vehicle FILE")
        channel = real.pwm_channel
        if real.kind == "pca9685":
            key = str(real.i2c_bus)
            sock, chips = self._buses.setdefault(key, (self.run_dir / f"pwm-i2c-{len(self._buses)}.sock", set()))
            chips.add(real.chip_address)
            return make_address("pca9685", str(sock), (real.chip_address, channel), mock=True, device=device).url
        tree, npwm = self._trees.get(real.pwm_chip, (self.run_dir / "pwm" / f"pwmchip{len(self._trees)}", 0))
        self._trees[real.pwm_chip] = (tree, max(npwm, channel + 1, 16))
        return make_address("pwm", str(tree), (channel,), mock=True, device=device).url

    def start(self) -> None:
        """Create the trees and start the buses (once for all the service's devices)."""
        if self._started:
            return
        from u2sa_hw.mocks.i2c_bus import MockI2cBus
        from u2sa_hw.mocks.pca9685_chip import Pca9685Chip
        from u2sa_hw.ports.pwm.port import make_sysfs_pwm_tree

        self._started = True
        for tree, npwm in self._trees.values():
            make_sysfs_pwm_tree(tree, npwm=npwm)
        for sock, chips in self._buses.values():
            bus = MockI2cBus(socket_path=str(sock))
            for address in sorted(chips):
                bus.add(Pca9685Chip(address=address))
            bus.start()
            self._objects.append(bus)

    def stop(self) -> None:
        """Stop the buses (the trees go with the run directory)."""
        for bus in self._objects:
            bus.stop()
        self._objects.clear()


class ReplayPwmDevice:
    """One recorded PWM output (``RAW.<channel name>``): present for the driver, its writes counted."""

    kind = "pwm"
    streamed = True

    def __init__(self, *, name: str, rig: PwmReplayRig) -> None:
        self.name = name
        self.rig = rig
        self.counts = {"recorded_writes": 0}

    def mock_address(self, real: DeviceAddress | None) -> str:
        """The replay output standing in for the recorded one (shared chips per service)."""
        return self.rig.add(self.name, real)

    def config_changes(self) -> dict[str, Any]:
        """Nothing besides the address."""
        return {}

    def start(self) -> None:
        """Start the service's replay outputs (shared)."""
        self.rig.start()

    def stop(self) -> None:
        """Stop them (shared; idempotent)."""
        self.rig.stop()

    def ready(self, pid: int | None, health: dict[str, str]) -> bool:
        """The servo driver has opened this channel (``<name>.port = open`` in its health)."""
        return health.get(f"{self.name}.port") == "open"

    def feed(self, record: Any) -> None:
        """A recorded write is the driver's output, not its input: only counted."""
        self.counts["recorded_writes"] += 1

    def pending(self) -> int:
        """Nothing to take: the driver's input is the republished commands."""
        return 0

    def report(self) -> dict[str, Any]:
        """Recorded writes passed (the writes themselves are compared by --compare)."""
        return {"kind": self.kind, **self.counts, "divergences": 0}
