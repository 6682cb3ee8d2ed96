"""PWM channels on a PCA9685 over I2C: the ``pca9685:<bus>:<i2c addr>`` backend of open_pwm.

``open_pca9685_pwm(device="rudder", address="pca9685:1:0x40", channel=3)`` drives
channel 3 of the chip at 0x40 on /dev/i2c-1; ``"pca9685:mock:/run/i2c.sock:0x40"`` drives
the mock chip on the mock I2C bus. The PwmChannel methods match the sysfs backend:
``set_pulse_ns``, ``set_pulse_us``, ``enable(on)``, ``close()``; every call is handed to
the tap as a ``RawPwmWrite``.

All channels of one chip share its frame period (PRE_SCALE). Channels opened in one
process share one I2C port and one chip record; the chip is only put to sleep to change
PRE_SCALE when it does not already hold the wanted value, so opening a second channel
(here or in another process) never disturbs the first. Opening a channel adopts the
pulse the chip is already producing (after a crashed driver, the servo keeps its
position rather than jumping), and ``close()`` stops the output like the sysfs backend.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from typing import Iterator

from u2sa_hw.ports.errors import PortClosed, PortError, PortUnavailable
from u2sa_hw.ports.i2c.port import MOCK_SCHEME, I2cPort, open_i2c_chip, parse_bus
from u2sa_hw.ports.pwm.port import tap_pwm_state
from u2sa_hw.ports.tap import Tap
from u2sa_hw.protocols import pca9685 as pca

SCHEME = "pca9685:"
log = logging.getLogger(__name__)


def parse_address(address: str, *, device: str) -> tuple[int | str, int]:
    """Split ``pca9685:<bus>:<i2c addr>`` into (bus, 7-bit address)."""
    fix = 'write it as "pca9685:<bus>:<i2c addr>", e.g. "pca9685:1:0x40" or "pca9685:mock:/run/i2c.sock:0x40"'
    if not isinstance(address, str) or not address.startswith(SCHEME):
        raise PortUnavailable(device, f"{address!r} is not a PCA9685 address", address=str(address), fix=fix)
    bus_text, _, addr_text = address[len(SCHEME):].rpartition(":")
    try:
        i2c_address = int(addr_text, 0)
    except ValueError:
        raise PortUnavailable(device, f"bad I2C address {addr_text!r} in {address!r}", address=address,
                              fix=fix) from None
    if not bus_text:
        raise PortUnavailable(device, f"no I2C bus in {address!r}", address=address, fix=fix)
    return parse_bus(bus_text, device=device), i2c_address


class Pca9685Controller:
    """One PCA9685 as this process sees it: its I2C port, frame period and open channels."""

    def __init__(self, *, bus: int | str, i2c_address: int, period_ns: int) -> None:
        self.device = "pca9685"  # channels re-raise the port's errors under their own names
        self.bus = bus           # an adapter number, or the mock I2C bus server's socket path
        self.i2c_address = i2c_address
        self.prescale = pca.prescale_for_period(period_ns)
        self.period_ns = pca.period_for_prescale(self.prescale)
        self.requested_period_ns = period_ns
        self.channels: set[int] = set()
        self.lock = threading.RLock()
        self._port: I2cPort | None = None

    def port(self) -> I2cPort:
        """The open I2C port, reopened and the chip set up again if the bus went away."""
        with self.lock:
            if self._port is None or not self._port.is_open:
                self._port = open_i2c_chip(device=self.device, bus=self.bus, chip=self.i2c_address)
                try:
                    self._configure(self._port)
                except Exception:
                    self._port.close()
                    raise
            return self._port

    def _configure(self, port: I2cPort) -> None:
        """Set PRE_SCALE for the frame (only if it differs), wake, auto-increment, restart."""
        mode1 = port.read_byte(pca.MODE1)
        keep = mode1 & ~(pca.MODE1_RESTART | pca.MODE1_SLEEP)
        awake = keep | pca.MODE1_AI
        if port.read_byte(pca.PRE_SCALE) != self.prescale:
            port.write_byte(pca.MODE1, keep | pca.MODE1_SLEEP)  # PRE_SCALE only takes writes asleep
            port.write_byte(pca.PRE_SCALE, self.prescale)
            mode1 = keep | pca.MODE1_SLEEP
        if mode1 == awake:
            return
        port.write_byte(pca.MODE1, awake)
        if mode1 & pca.MODE1_SLEEP:
            time.sleep(pca.WAKE_DELAY_S * 2)  # oscillator settling before RESTART (data sheet: >= 500 µs)
        if port.read_byte(pca.MODE1) & pca.MODE1_RESTART:
            port.write_byte(pca.MODE1, awake | pca.MODE1_RESTART)

    def write_counts(self, channel: int, high_counts: int) -> None:
        """Program *channel* high for *high_counts* of 4096 (one 4-byte auto-increment write)."""
        with self.lock:
            self.port().write_block(pca.led_register(channel), pca.pulse_led_bytes(high_counts))

    def read_counts(self, channel: int) -> int:
        """The high counts *channel* is programmed with."""
        with self.lock:
            return pca.high_counts(self.port().read_block(pca.led_register(channel), 4))

    def close(self) -> None:
        """Release the I2C port."""
        with self.lock:
            if self._port is not None:
                self._port.close()
                self._port = None


_chips: dict[tuple[int | str, int], Pca9685Controller] = {}
_chips_lock = threading.Lock()


def _attach(*, device: str, address: str, bus: int | str, i2c_address: int, channel: int,
            period_ns: int) -> Pca9685Controller:
    """The shared chip record for (bus, address), created or checked for a matching period; errors name *address*."""
    with _chips_lock:
        chip = _chips.get((bus, i2c_address))
        if chip is not None and chip.channels and pca.prescale_for_period(period_ns) != chip.prescale:
            raise PortUnavailable(device, f"the PCA9685 at 0x{i2c_address:02x} runs a {chip.period_ns} ns frame for "
                                  f"channels {sorted(chip.channels)}; channel {channel} asks {period_ns} ns",
                                  address=address,
                                  fix="all channels of one PCA9685 share one period: "
                                      f"use period_ns={chip.requested_period_ns}")
        if chip is not None and channel in chip.channels:
            raise PortUnavailable(device, f"PCA9685 channel {channel} at 0x{i2c_address:02x} is already open",
                                  address=address,
                                  fix="give each actuator its own channel in the vehicle config")
        if chip is None or not chip.channels:
            chip = Pca9685Controller(bus=bus, i2c_address=i2c_address, period_ns=period_ns)
            _chips[(bus, i2c_address)] = chip
        chip.channels.add(channel)
        return chip


def _detach(chip: Pca9685Controller, channel: int) -> None:
    with _chips_lock:
        chip.channels.discard(channel)
        if not chip.channels:
            chip.close()
            if _chips.get((chip.bus, chip.i2c_address)) is chip:
                del _chips[(chip.bus, chip.i2c_address)]


class Pca9685PwmChannel:
    """One PWM output of a PCA9685, with the PwmChannel methods of the sysfs backend.

    ``duty_ns`` is the pulse last set (the chip makes the nearest of its 4096 counts),
    ``enabled`` whether the output runs, ``period_ns`` the frame the chip actually runs
    (the PRE_SCALE step nearest the request). Port errors name this channel's device.
    """

    def __init__(self, *, device: str, address: str, channel: int, chip: Pca9685Controller, tap: Tap | None) -> None:
        self.device = device
        self.address = address
        self.channel = channel
        self._chip = chip
        self._tap = tap
        self._open = True
        with self._errors_named():
            counts = chip.read_counts(channel)
        self.enabled = counts > 0
        self.duty_ns = round(counts * pca.count_ns(chip.prescale))
        self._tap_state()

    @property
    def period_ns(self) -> int:
        """The frame period the chip runs, in ns."""
        return self._chip.period_ns

    @property
    def is_open(self) -> bool:
        """False after close()."""
        return self._open

    def set_pulse_ns(self, ns: int) -> None:
        """Set the high time per frame in ns (0..period); takes effect now if enabled."""
        ns = int(ns)
        if not 0 <= ns <= self.period_ns:
            raise ValueError(f"{self.device}: pulse {ns} ns is outside 0..{self.period_ns} ns "
                             f"(the frame of {self.address})")
        self._apply(duty_ns=ns, enabled=self.enabled)

    def set_pulse_us(self, us: float) -> None:
        """Set the high time per frame in µs."""
        self.set_pulse_ns(round(us * 1000))

    def enable(self, on: bool) -> None:
        """Turn the output on (at the set pulse) or fully off."""
        self._apply(duty_ns=self.duty_ns, enabled=bool(on))

    def close(self) -> None:
        """Stop the output and release the channel (idempotent; a vanished bus is fine)."""
        if not self._open:
            return
        try:
            self.enable(False)
        except PortError as exc:
            log.debug("%s: stopping PCA9685 channel %d on close: %s", self.device, self.channel, exc)
        self._open = False
        _detach(self._chip, self.channel)

    def __enter__(self) -> "Pca9685PwmChannel":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return (f"<Pca9685PwmChannel {self.device} {self.address} ch{self.channel} period={self.period_ns} "
                f"duty={self.duty_ns} enabled={self.enabled}>")

    def _apply(self, *, duty_ns: int, enabled: bool) -> None:
        """Write the chip when the output changes; tap every change of state."""
        if not self._open:
            raise PortClosed(self.device, f"PCA9685 channel {self.channel} is closed", address=self.address,
                             fix="open the channel again")
        if (duty_ns, enabled) == (self.duty_ns, self.enabled):
            return
        if enabled or self.enabled:  # a disabled output is already full-off: nothing to write
            counts = pca.counts_for_pulse(duty_ns, self._chip.prescale) if enabled else 0
            with self._errors_named():
                self._chip.write_counts(self.channel, counts)
        self.duty_ns, self.enabled = duty_ns, enabled
        self._tap_state()

    def _tap_state(self) -> None:
        tap_pwm_state(self._tap, device=self.device, channel=self.channel, period_ns=self.period_ns,
                      duty_ns=self.duty_ns, enabled=self.enabled)

    @contextlib.contextmanager
    def _errors_named(self) -> Iterator[None]:
        """Re-raise the shared I2C port's errors as this channel's, same kind and fix."""
        try:
            yield
        except PortError as exc:
            raise renamed_error(exc, device=self.device, address=self.address) from exc


def renamed_error(exc: PortError, *, device: str, address: str) -> PortError:
    """*exc* (same class, message and fix) attributed to *device* at *address*."""
    text = str(exc)
    reason = text.split(": ", 1)[1] if ": " in text else text
    if exc.fix:
        reason = reason.removesuffix(f"; fix: {exc.fix}")
    return type(exc)(device, reason, address=address, fix=exc.fix)


def open_pca9685_pwm(*, device: str, address: str, channel: int, period_ns: int = 20_000_000,
                     tap: Tap | None = None) -> Pca9685PwmChannel:
    """Open *channel* (0..15) of the PCA9685 at *address* (``pca9685:<bus>:<i2c addr>``) with a frame of *period_ns*."""
    bus, i2c_address = parse_address(address, device=device)
    return open_pca9685_channel(device=device, address=address, bus=bus if isinstance(bus, int) else
                                bus[len(MOCK_SCHEME):], i2c_address=i2c_address, channel=channel, period_ns=period_ns,
                                tap=tap)


def open_pca9685_channel(*, device: str, address: str, bus: int | str, i2c_address: int, channel: int,
                         period_ns: int = 20_000_000, tap: Tap | None = None) -> Pca9685PwmChannel:
    """Open *channel* (0..15) of the PCA9685 at *i2c_address* on *bus* (an adapter number, or the mock I2C bus
    server's socket path) with a frame of *period_ns*: the typed parts of a parsed address, as they are.
    *address* is what errors and taps name."""
    if isinstance(channel, bool) or not isinstance(channel, int) or not 0 <= channel < pca.CHANNELS:
        raise PortUnavailable(device, f"PCA9685 channel must be 0..{pca.CHANNELS - 1}, got {channel!r}",
                              address=address, fix="use the channel number printed on the board")
    try:
        pca.prescale_for_period(period_ns)
    except ValueError as exc:
        raise PortUnavailable(device, str(exc), address=address,
                              fix="servos and ESCs use 20_000_000 ns (50 Hz)") from None
    chip = _attach(device=device, address=address, bus=bus, i2c_address=i2c_address, channel=channel,
                   period_ns=period_ns)
    try:
        return Pca9685PwmChannel(device=device, address=address, channel=channel, chip=chip, tap=tap)
    except BaseException:
        _detach(chip, channel)
        raise
