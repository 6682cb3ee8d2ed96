"""The PWM address grammar: ``pwm://pwmchipN/CHANNEL`` (under /sys/class/pwm), ``mock+pwm:///DIR/CHANNEL``.

A PCA9685's addresses (``pca9685://BUS/CHIP/CHANNEL``) are I2C ones: :func:`u2sa_hw.ports.i2c.grammar.parse_i2c`.
"""

from __future__ import annotations

from u2sa_hw.ports.address_schemes import SYSFS_PWM, Fail, Parsed, UrlParts, channel_number, split_last

PWM_PARAMS: tuple[str, ...] = ()
PCA9685_PARAMS: tuple[str, ...] = ()


def parse_pwm(parts: UrlParts, fail: Fail) -> Parsed:
    """``pwm://pwmchipN/CHANNEL`` (under /sys/class/pwm; mock: any directory)."""
    full = (f"{SYSFS_PWM}/{parts.netloc}" if parts.netloc else "") + parts.path
    if parts.mock and parts.netloc:
        raise fail("a mock pwm address is mock+pwm:///path/to/chipdir/CHANNEL")
    location, tail = split_last(full, 1, "CHIP/CHANNEL", fail)
    channel = channel_number(tail[0], fail)
    if not parts.mock and not location.startswith(SYSFS_PWM + "/"):
        raise fail(f"a real pwm chip lives under {SYSFS_PWM}; a directory elsewhere is mock+pwm:///DIR/CHANNEL")
    return ("mock" if parts.mock else "sysfs"), location, (channel,)
