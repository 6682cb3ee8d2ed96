"""The pilot's sticks as manual commands: the software half of the RC mux (kind ``rc_mux``).

A hardware RC mux can switch only the PWM wires that pass through it. Every other actuator
(CAN motor controllers, PWM boards on I2C, GPIO outputs) is switched in software: in manual
the rc_mux service turns the stick pulses into Percentage Commands on ``MANUAL_CMD`` through
the profile's ``[safety.manual_mixer]`` (the control system's mixers: differential,
twin thruster, Ackermann), and each such actuator obeys them only in manual
(:mod:`u2sa_hw.safety.gate`). A stick without a valid pulse within the signal timeout
counts as centred, and no commands go out without a valid mode signal.
"""

from __future__ import annotations

from typing import Mapping

from u2sa_hw import lcmtypes as t
from u2sa_hw.safety.config import ManualMixerSpec


class ManualSticks:
    """Stick pulse widths -> actuator percentages through the profile's manual mixer."""

    def __init__(self, spec: ManualMixerSpec) -> None:
        self.spec = spec
        self.mixer = spec.build()
        self.sent = 0

    @property
    def channels(self) -> tuple[str, str]:
        """(throttle channel, steering channel) of the RC receiver."""
        return self.spec.throttle_channel, self.spec.steering_channel

    def percentages(self, widths_us: Mapping[str, float]) -> dict[str, float]:
        """Each mixed actuator's percentage for the present stick widths (0 us: no pulse, centred)."""
        throttle = self.spec.stick_percent(widths_us.get(self.spec.throttle_channel, 0.0))
        turn = self.spec.stick_percent(widths_us.get(self.spec.steering_channel, 0.0))
        return self.mixer.mix(turn, throttle)

    def commands(self, widths_us: Mapping[str, float]) -> list[t.PercentageCommand]:
        """One PercentageCommand per mixed actuator (for ``MANUAL_CMD``)."""
        out = []
        for actuator, pct in self.percentages(widths_us).items():
            cmd = t.PercentageCommand()
            cmd.base.actuator_name, cmd.percentage = actuator, float(pct)
            out.append(cmd)
        self.sent += len(out)
        return out
