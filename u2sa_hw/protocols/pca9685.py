"""NXP PCA9685 16-channel 12-bit PWM controller: registers, bits and timing arithmetic.

Shared by the PWM backend (u2sa_hw/ports/pwm/pca9685.py) and the mock chip
(mock_devices/pca9685_chip.py). From the NXP PCA9685 product data sheet (rev. 4):
the frame is 4096 counts of (PRE_SCALE + 1) oscillator periods; each channel goes high at
its ON count and low at its OFF count; bit 4 of LEDn_ON_H is "full on", bit 4 of
LEDn_OFF_H "full off" (full off wins). PRE_SCALE can only be written while MODE1.SLEEP = 1.
"""

from __future__ import annotations

I2C_ADDRESS = 0x40  # all address pins low
ALLCALL_ADDRESS = 0x70

MODE1 = 0x00
MODE2 = 0x01
SUBADR1 = 0x02
SUBADR2 = 0x03
SUBADR3 = 0x04
ALLCALLADR = 0x05
LED0_ON_L = 0x06
LED_STRIDE = 4  # ON_L, ON_H, OFF_L, OFF_H per channel
CHANNELS = 16
LED15_OFF_H = LED0_ON_L + CHANNELS * LED_STRIDE - 1  # 0x45
ALL_LED_ON_L = 0xFA
ALL_LED_ON_H = 0xFB
ALL_LED_OFF_L = 0xFC
ALL_LED_OFF_H = 0xFD
PRE_SCALE = 0xFE
TEST_MODE = 0xFF

# MODE1 bits
MODE1_RESTART = 0x80
MODE1_EXTCLK = 0x40
MODE1_AI = 0x20
MODE1_SLEEP = 0x10
MODE1_SUB1 = 0x08
MODE1_SUB2 = 0x04
MODE1_SUB3 = 0x02
MODE1_ALLCALL = 0x01

# MODE2 bits
MODE2_INVRT = 0x10
MODE2_OCH = 0x08
MODE2_OUTDRV = 0x04

# Bit 4 of LEDn_ON_H / LEDn_OFF_H
FULL_BIT = 0x10

# Power-on register values
MODE1_RESET = MODE1_SLEEP | MODE1_ALLCALL  # 0x11
MODE2_RESET = MODE2_OUTDRV  # 0x04
PRE_SCALE_RESET = 0x1E  # 200 Hz with the 25 MHz oscillator
SUBADR_RESET = (0xE2, 0xE4, 0xE8)
ALLCALLADR_RESET = 0xE0

OSCILLATOR_HZ = 25_000_000
COUNTS = 4096
PRE_SCALE_MIN = 3  # writes below 3 are forced to 3 by the chip
PRE_SCALE_MAX = 255
WAKE_DELAY_S = 0.0005  # oscillator settling after clearing SLEEP, before RESTART


def led_register(channel: int) -> int:
    """LEDn_ON_L of *channel* (0..15); ON_H, OFF_L, OFF_H follow it."""
    if not 0 <= channel < CHANNELS:
        raise ValueError(f"PCA9685 channel must be 0..{CHANNELS - 1}, got {channel}")
    return LED0_ON_L + LED_STRIDE * channel


def prescale_for_period(period_ns: int, *, oscillator_hz: int = OSCILLATOR_HZ) -> int:
    """The PRE_SCALE value whose frame is nearest *period_ns* (data sheet eq. 1)."""
    if period_ns <= 0:
        raise ValueError(f"PWM period must be positive, got {period_ns} ns")
    value = round(oscillator_hz * period_ns / (COUNTS * 1e9)) - 1
    lowest = period_for_prescale(PRE_SCALE_MIN, oscillator_hz=oscillator_hz)
    highest = period_for_prescale(PRE_SCALE_MAX, oscillator_hz=oscillator_hz)
    if not PRE_SCALE_MIN <= value <= PRE_SCALE_MAX:
        raise ValueError(f"PWM period {period_ns} ns is outside the PCA9685 range "
                         f"{lowest}..{highest} ns ({1e9 / highest:.0f}..{1e9 / lowest:.0f} Hz)")
    return value


def period_for_prescale(prescale: int, *, oscillator_hz: int = OSCILLATOR_HZ) -> int:
    """The frame period in ns that PRE_SCALE = *prescale* gives."""
    return round(COUNTS * (max(prescale, PRE_SCALE_MIN) + 1) * 1e9 / oscillator_hz)


def count_ns(prescale: int, *, oscillator_hz: int = OSCILLATOR_HZ) -> float:
    """The length of one of the 4096 counts in ns for PRE_SCALE = *prescale*."""
    return (max(prescale, PRE_SCALE_MIN) + 1) * 1e9 / oscillator_hz


def counts_for_pulse(pulse_ns: float, prescale: int, *, oscillator_hz: int = OSCILLATOR_HZ) -> int:
    """The number of high counts (0..4096) nearest a pulse of *pulse_ns*."""
    counts = round(pulse_ns / count_ns(prescale, oscillator_hz=oscillator_hz))
    return max(0, min(COUNTS, counts))


def led_bytes(on_count: int, off_count: int, *, full_on: bool = False, full_off: bool = False) -> bytes:
    """The four bytes ON_L, ON_H, OFF_L, OFF_H for one channel."""
    if not (0 <= on_count < COUNTS and 0 <= off_count < COUNTS):
        raise ValueError(f"PCA9685 ON/OFF counts must be 0..4095, got {on_count}/{off_count}")
    on_h = (on_count >> 8) | (FULL_BIT if full_on else 0)
    off_h = (off_count >> 8) | (FULL_BIT if full_off else 0)
    return bytes((on_count & 0xFF, on_h, off_count & 0xFF, off_h))


def pulse_led_bytes(high_counts: int) -> bytes:
    """LEDn bytes for a pulse of *high_counts* starting at count 0 (0 = off, 4096 = on)."""
    if high_counts <= 0:
        return led_bytes(0, 0, full_off=True)
    if high_counts >= COUNTS:
        return led_bytes(0, 0, full_on=True)
    return led_bytes(0, high_counts)


def high_counts(led: bytes) -> int:
    """How many of the 4096 counts a channel is high, from its four LEDn bytes."""
    on = led[0] | ((led[1] & 0x0F) << 8)
    off = led[2] | ((led[3] & 0x0F) << 8)
    if led[3] & FULL_BIT:
        return 0
    if led[1] & FULL_BIT:
        return COUNTS
    return (off - on) % COUNTS
