"""Register-level model of the NXP PCA9685 16-channel PWM controller.

What the model keeps from the data sheet (rev. 4):
* power-on values: MODE1 0x11 (asleep, ALLCALL), MODE2 0x04, PRE_SCALE 0x1E, every
  channel full-off (LEDn_OFF_H bit 4);
* MODE1.AI: with auto-increment the register pointer advances after each byte
  (0x45 wraps to 0x00); without it a multi-byte write keeps hitting one register;
* PRE_SCALE only takes writes while MODE1.SLEEP = 1; values below 3 read back as 3;
* outputs run only while awake; going to sleep with a channel running sets
  MODE1.RESTART, and the channels stay stopped after waking until RESTART is written
  with 1 (at least 500 µs after clearing SLEEP, otherwise the restart is lost) or a PWM
  register is written; the ALL_LED registers write every channel and read as 0;
* MODE2.INVRT inverts the outputs.
Not modelled: EXTCLK, sub-addresses and ALLCALL, the OE pin, the software-reset call.

``pulse_width_us(channel)`` is what the simulation and tests read: the high time of the
channel's output in microseconds, from PRE_SCALE, the ON/OFF counts and the oscillator.
"""

from __future__ import annotations

import time

from u2sa_hw.mocks.i2c_chip import RegisterChip
from u2sa_hw.protocols import pca9685 as pca

_LED_REGISTERS = range(pca.LED0_ON_L, pca.LED15_OFF_H + 1)
_ALL_LED = range(pca.ALL_LED_ON_L, pca.ALL_LED_OFF_H + 1)


class Pca9685Chip(RegisterChip):
    """A PCA9685 at 0x40 (0x40..0x7F by its address pins) with an *oscillator_hz* clock."""

    write_only = frozenset(_ALL_LED)
    reset_values = {
        pca.MODE1: pca.MODE1_RESET, pca.MODE2: pca.MODE2_RESET, pca.SUBADR1: pca.SUBADR_RESET[0],
        pca.SUBADR2: pca.SUBADR_RESET[1], pca.SUBADR3: pca.SUBADR_RESET[2], pca.ALLCALLADR: pca.ALLCALLADR_RESET,
        pca.PRE_SCALE: pca.PRE_SCALE_RESET,
        **{pca.led_register(ch) + 3: pca.FULL_BIT for ch in range(pca.CHANNELS)},
    }

    def __init__(self, *, address: int = pca.I2C_ADDRESS, oscillator_hz: int = pca.OSCILLATOR_HZ) -> None:
        self.oscillator_hz = oscillator_hz
        self._woke_at = 0.0
        self._led_written = False
        self.lost_restarts = 0  # RESTART writes ignored because they came < 500 µs after waking
        super().__init__(address=address)

    @property
    def asleep(self) -> bool:
        """True while MODE1.SLEEP is set (oscillator off, outputs off)."""
        return bool(self.peek(pca.MODE1) & pca.MODE1_SLEEP)

    @property
    def restart_pending(self) -> bool:
        """True while MODE1.RESTART is set: the channels wait for a restart."""
        return bool(self.peek(pca.MODE1) & pca.MODE1_RESTART)

    @property
    def prescale(self) -> int:
        """The PRE_SCALE register."""
        return self.peek(pca.PRE_SCALE)

    def frame_period_us(self) -> float:
        """The PWM frame length in microseconds."""
        return pca.period_for_prescale(self.prescale, oscillator_hz=self.oscillator_hz) / 1000.0

    def frame_rate_hz(self) -> float:
        """The PWM frame rate in Hz."""
        return 1e6 / self.frame_period_us()

    def high_counts(self, channel: int) -> int:
        """How many of the 4096 counts *channel* is programmed high (ignoring sleep/restart)."""
        with self._lock:
            reg = pca.led_register(channel)
            return pca.high_counts(bytes(self._regs[reg:reg + 4]))

    def pulse_width_us(self, channel: int) -> float:
        """The high time of *channel*'s output in µs (0 while asleep or waiting for restart)."""
        with self._lock:
            running = not (self.asleep or self.restart_pending)
            counts = self.high_counts(channel) if running else 0
            if self._regs[pca.MODE2] & pca.MODE2_INVRT and running:
                counts = pca.COUNTS - counts
            return counts * pca.count_ns(self.prescale, oscillator_hz=self.oscillator_hz) / 1000.0

    def pulse_widths_us(self) -> list[float]:
        """``pulse_width_us`` of all 16 channels."""
        with self._lock:
            return [self.pulse_width_us(ch) for ch in range(pca.CHANNELS)]

    def next_register(self, register: int) -> int:
        """Auto-increment only with MODE1.AI; LED15_OFF_H and 0xFF wrap to MODE1."""
        if not self._regs[pca.MODE1] & pca.MODE1_AI:
            return register
        if register in (pca.LED15_OFF_H, pca.TEST_MODE):
            return pca.MODE1
        return register + 1

    def write_register(self, register: int, value: int) -> None:
        """MODE1 sleep/restart rules, PRE_SCALE only while asleep, ALL_LED fan-out."""
        if register == pca.MODE1:
            self._write_mode1(value)
        elif register == pca.PRE_SCALE:
            if self.asleep:
                self._regs[pca.PRE_SCALE] = max(value, pca.PRE_SCALE_MIN)
        elif register in _ALL_LED:
            offset = register - pca.ALL_LED_ON_L
            for ch in range(pca.CHANNELS):
                self._regs[pca.led_register(ch) + offset] = value
            self._led_written = True
        else:
            if register in _LED_REGISTERS:
                self._led_written = True
            super().write_register(register, value)

    def end_write(self, register: int, length: int) -> None:
        """A PWM register write followed by STOP clears RESTART (MODE2.OCH = 0 behaviour)."""
        if self._led_written:
            self._led_written = False
            self._regs[pca.MODE1] &= ~pca.MODE1_RESTART

    def _write_mode1(self, value: int) -> None:
        old = self._regs[pca.MODE1]
        restart = old & pca.MODE1_RESTART
        was_asleep, sleep = bool(old & pca.MODE1_SLEEP), bool(value & pca.MODE1_SLEEP)
        now = time.monotonic()
        if sleep and not was_asleep and any(self.high_counts(ch) for ch in range(pca.CHANNELS)):
            restart = pca.MODE1_RESTART
        if was_asleep and not sleep:
            self._woke_at = now
        if value & pca.MODE1_RESTART and restart and not sleep:
            if now - self._woke_at >= pca.WAKE_DELAY_S:
                restart = 0
            else:
                self.lost_restarts += 1
        self._regs[pca.MODE1] = (value & ~pca.MODE1_RESTART) | restart
