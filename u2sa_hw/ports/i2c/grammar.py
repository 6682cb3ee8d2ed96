"""The I2C address grammar: ``i2c://BUS/CHIP``, ``mock+i2c:///BUS.sock/CHIP``; and ``pca9685://BUS/CHIP/CHANNEL``,
whose bus part is the same.
"""

from __future__ import annotations

import math

from u2sa_hw.ports.address_schemes import (MOCK_PREFIX, Fail, Parsed, UrlParts, channel_number, chip_address,
                                           split_last)

I2C_PARAMS = ("timeout", "paced")   # mock+i2c only: timeout=S, the client's wait for the server's answer;
                                   # paced=true: the bus holds each data read until its data exists (a replay)


def mock_i2c_timeout(text: str, fail: Fail) -> float:
    """``timeout=`` of a mock+i2c address: seconds, a finite number > 0, else *fail*."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise fail(f"timeout={text!r} must be a number of seconds > 0 (how long the client waits for the mock "
                   "I2C bus server's answer), e.g. timeout=60")
    return value


def parse_i2c(parts: UrlParts, fail: Fail) -> Parsed:
    """``i2c://BUS/CHIP`` and ``pca9685://BUS/CHIP/CHANNEL`` (mock: a bus socket path instead of BUS).

    ``timeout=S`` (how long the client waits for the server's answer; the mock client's default
    is 2 s) and ``paced=true`` (the bus holds each data read until its data exists, so a driver
    reads back to back instead of on its timer) are taken only by ``mock+i2c`` addresses: a
    replay's bus holds a data read until the player releases it (docs/replay.md), where a real
    adapter times out in its kernel driver and a real chip is read on the driver's timer.
    """
    kind = parts.kind
    if "timeout" in parts.params:
        if not parts.mock:
            raise fail("timeout= is only for mock+i2c addresses (how long the client waits for the mock bus "
                       "server); a real adapter's timeout is its kernel driver's: remove timeout=")
        mock_i2c_timeout(parts.params["timeout"], fail)
    if "paced" in parts.params:
        if not parts.mock:
            raise fail("paced= is only for mock+i2c addresses (a replay's bus, which holds each data read until "
                       "its data exists); a real chip is read on the driver's timer: remove paced=")
        if parts.params["paced"].lower() not in ("true", "false"):
            raise fail(f"paced={parts.params['paced']!r} must be true or false")
    count = 1 if kind == "i2c" else 2
    what = "BUS/CHIP" if kind == "i2c" else "BUS/CHIP/CHANNEL"
    if parts.mock:
        if parts.netloc:
            raise fail(f"a mock {kind} address is {MOCK_PREFIX}{kind}:///path/to/bus.sock/{what[4:]}")
        backend = "mock"
        location, tail = split_last(parts.path, count, f"/path/to/bus.sock/{what[4:]}", fail)
    else:
        tail = parts.path.strip("/").split("/") if parts.path.strip("/") else []
        if not parts.netloc.isdigit() or len(tail) != count:
            raise fail(f"expected {kind}://{what} with BUS the adapter number (1 for /dev/i2c-1)")
        backend, location = "smbus", parts.netloc
    numbers: tuple[int, ...] = (chip_address(tail[0], fail),)
    if kind == "pca9685":
        numbers += (channel_number(tail[1], fail, 16),)
    return backend, location, numbers
