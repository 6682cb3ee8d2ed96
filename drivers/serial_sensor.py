"""The part every line-oriented serial sensor shares: port, reconnect, taps, counters, health.

:class:`SerialLineSensor` opens its port through :class:`~u2sa_hw.ports.ReconnectingPort`
(so an unplugged device is reported in health and reopened with backoff while the service
keeps running), reads whole lines, and hands each to :meth:`handle_line`; when the line
stays quiet for ``epoch_gap_s`` it calls :meth:`handle_idle` (the end of a burst). With
``record_raw`` every chunk read is published as ``RawSerial`` on ``RAW.<device>``.

Its status is ``ok`` or ``degraded``; the reason (port down, no data, or the subclass's
:meth:`problem`, e.g. "no fix") is the ``degraded_reason`` health detail.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, ClassVar

from u2sa_hw import lcmtypes as t
from u2sa_hw.abstract import ProprioceptiveSensor
from u2sa_hw.config import ConfigError, field
from u2sa_hw.ports import PortClosed, PortIOError, PortUnavailable, ReconnectingPort
from u2sa_hw.ports.serial_port import SerialPort, open_serial
from u2sa_hw.ports.tap import raw_channel

BAUDRATES = (4800, 9600, 19200, 38400, 57600, 115200)
BYTESIZES = (5, 6, 7, 8)
PARITIES = ("N", "E", "O", "M", "S")  # none, even, odd, mark, space (pyserial's letters)
STOPBITS = (1.0, 1.5, 2.0)
_PORT_FIELDS = ("port", "baudrate", "bytesize", "parity", "stopbits", "device_name", "epoch_gap_s")


class SerialLineSensor(ProprioceptiveSensor):
    """A proprioceptive sensor that reads NMEA-style lines from one serial device."""

    CONFIG = (
        field("port", "", "device path (/dev/u2sa/NAME) or pyserial URL"),
        field("baudrate", 9600, "one of 4800, 9600, 19200, 38400, 57600, 115200"),
        field("bytesize", 8, "data bits: 5, 6, 7 or 8", choices=BYTESIZES),
        field("parity", "N", "parity: N (none), E (even), O (odd), M (mark) or S (space)", choices=PARITIES),
        field("stopbits", 1.0, "stop bits: 1, 1.5 or 2", choices=STOPBITS),
        field("device_name", "", "device name in errors and RAW.<device> (empty: the service name)"),
        field("record_raw", False, "publish every chunk read as RawSerial on RAW.<device>"),
        field("stale_after_s", 2.0, "no valid sentence for this long -> degraded, data stale", gt=0),
        field("epoch_gap_s", 0.05, "this much silence on the line ends a burst of sentences (and is the read timeout)", gt=0),
    )
    EXAMPLE_PORT: ClassVar[str] = "/dev/u2sa/gps"

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.check_config()
        self.lines = 0
        self.malformed = 0
        self.ignored = 0
        self.published = 0
        self.noise_bytes = 0
        self.stale_events = 0  # times the data went from fresh to stale (the device fell silent)
        self._stale = False
        self._stale_lock = threading.Lock()
        self.bad_checksums: dict[str, int] = {}
        self.last_valid: float | None = None  # monotonic time of the last sentence that parsed
        self._started = time.monotonic()
        self._port: ReconnectingPort[SerialPort] | None = None
        self._reopen = False
        self._problem = ""

    # -- config ------------------------------------------------------------------------------
    def check_config(self) -> None:
        """Refuse a config this driver cannot run with (ConfigError names the field and the fix)."""
        port, baud = self.config.get("port"), self.config.get("baudrate")
        if not port.strip():
            raise ConfigError(f"service '{self.name}': no serial port configured; set port = \"{self.EXAMPLE_PORT}\" "
                              "(or a pyserial URL) in the profile's settings or the service config")
        if baud not in BAUDRATES:
            raise ConfigError(f"service '{self.name}': baudrate {baud} is not supported; use one of "
                              f"{', '.join(map(str, BAUDRATES))} (the device's configured rate)")
        for key in ("stale_after_s", "epoch_gap_s"):
            if not self.config.get(key) > 0:
                raise ConfigError(f"service '{self.name}': {key} must be > 0, got {self.config.get(key)!r}")

    @property
    def framing(self) -> str:
        """The configured framing as data bits, parity, stop bits (``8N1``, ``7E2``, ``8N1.5``)."""
        stopbits = self.config.get("stopbits")
        return f"{self.config.get('bytesize')}{self.config.get('parity')}{stopbits:g}"

    @property
    def device_name(self) -> str:
        """The device's name in port errors and taps (``device_name``, else the service name)."""
        return self.config.get("device_name").strip() or self.name

    def on_config_change(self, name: str, value: Any) -> None:
        """Check the new config; a port, framing, device name or gap change reopens the port."""
        self.check_config()
        if name in _PORT_FIELDS:
            self._reopen = True
        if name == "record_raw" and value:
            self.register_publisher(raw_channel(self.device_name), t.RawSerial)

    # -- port ----------------------------------------------------------------------------------
    def _open(self) -> SerialPort:
        stopbits = self.config.get("stopbits")
        return open_serial(self.config.get("port"), device=self.device_name, baudrate=self.config.get("baudrate"),
                           bytesize=self.config.get("bytesize"), parity=self.config.get("parity"),
                           stopbits=int(stopbits) if stopbits.is_integer() else stopbits,
                           timeout=self.config.get("epoch_gap_s"), tap=self._tap)

    def _tap(self, record: t.RawSerial) -> None:
        if self.config.get("record_raw"):
            self.publish(raw_channel(self.device_name), record)

    def _new_port(self) -> None:
        if self._port is not None:
            self._port.close()
        self._port = ReconnectingPort(self._open, device=self.device_name)

    def setup(self) -> None:
        """Create the reconnecting port (opened by the run loop)."""
        if self.config.get("record_raw"):
            self.register_publisher(raw_channel(self.device_name), t.RawSerial)
        self._new_port()

    def run(self) -> None:
        """Read lines until stopped; survive port loss, bad bytes and silence."""
        assert self._port is not None, "setup() creates the port"
        while self.wait(0.0):
            if self._reopen:
                self._reopen = False
                self.on_port_lost()
                self._new_port()
            reconnecting = self._port
            try:
                port = reconnecting.get()
            except PortUnavailable:
                self.refresh_status()
                self.wait(min(0.5, max(0.02, reconnecting.retry_in())))
                continue
            except PortClosed:
                break  # closed by kill()
            try:
                line = port.readline()
            except (PortClosed, PortIOError) as exc:
                reconnecting.lost(exc, port=port)
                self.error(str(exc))
                self.on_port_lost()
                continue
            if line:
                self.lines += 1
                self._handle(line)
            else:
                self.handle_idle()
            self.refresh_status()

    def _handle(self, line: bytes) -> None:
        try:
            self.handle_line(line, time.time())
        except Exception as exc:  # noqa: BLE001 - one unexpected line must not end the driver
            self.malformed += 1
            self.logger.exception("%s: line %r could not be handled: %s", self.name, line[:80], exc)

    def kill(self) -> None:
        """Close the port, then stop."""
        if self._port is not None:
            self._port.close()
        super().kill()

    # -- for subclasses ----------------------------------------------------------------------
    def handle_line(self, line: bytes, received: float) -> None:
        """One complete line from the device; *received* is the wall time (s) it was read."""
        raise NotImplementedError

    def handle_idle(self) -> None:
        """The line was quiet for ``epoch_gap_s`` (the end of a burst)."""

    def on_port_lost(self) -> None:
        """The port went away (or is being reopened): drop partial state."""

    def problem(self) -> str:
        """Why the measurement is degraded beyond port and data (e.g. ``"no fix"``); ``""`` when fine."""
        return ""

    def sensor_details(self) -> dict[str, Any]:
        """The subclass's health details."""
        return {}

    # -- counting ------------------------------------------------------------------------------
    def count_valid(self, *, noise_bytes: int = 0) -> None:
        """A sentence parsed (the data is fresh); *noise_bytes* of line noise preceded it."""
        self.last_valid = time.monotonic()
        self.noise_bytes += noise_bytes

    def count_bad_checksum(self, kind: str, detail: str) -> None:
        """A sentence with a wrong checksum was dropped; logged once per sentence kind."""
        seen = self.bad_checksums.get(kind, 0)
        self.bad_checksums[kind] = seen + 1
        if not seen:
            self.logger.warning("%s: dropping %s sentences with bad checksums (logged once per kind; counted in "
                                "health): %s", self.device_name, kind, detail)

    def count_malformed(self, detail: str) -> None:
        """A line that is no sentence (noise, no checksum, bad fields) was dropped."""
        self.malformed += 1
        level = logging.INFO if self.malformed == 1 else logging.DEBUG  # the first one says what is going on
        self.logger.log(level, "%s: dropping malformed line (counted in health): %s", self.device_name, detail)

    # -- status and health -------------------------------------------------------------------
    def data_age(self) -> float | None:
        """Seconds since the last valid sentence (None before the first)."""
        return None if self.last_valid is None else time.monotonic() - self.last_valid

    def refresh_status(self) -> str:
        """Recompute ``status`` ("ok"/"degraded") and the reason; returns the reason."""
        reason = ""
        port = self._port
        age = self.data_age()
        limit = self.config.get("stale_after_s")
        if port is not None and port.state != "open":
            reason = f"port {port.state}"  # the error itself is the port_error detail
        elif age is None and time.monotonic() - self._started > limit:
            reason = "no data"
        elif age is not None and age > limit:
            reason = f"no data for {age:.1f} s"
        else:
            reason = self.problem()
        stale = age is not None and age > limit
        with self._stale_lock:  # the run loop and the health thread both get here
            went_stale = stale and not self._stale
            self._stale = stale
            if went_stale:
                self.stale_events += 1
        if went_stale:
            self.logger.warning("%s: no valid sentence for %.1f s (data stale; counted in stale_events)",
                                self.device_name, age)
        self._problem = reason
        if self.status != "stopping":
            self.status = "degraded" if reason else "ok"
        return reason

    def health_details(self) -> dict[str, Any]:
        """Port state, counters, data freshness and the subclass's details."""
        reason = self.refresh_status()
        port = self._port
        age = self.data_age()
        stale = age is None or age > self.config.get("stale_after_s")
        open_port = port.port if port else None  # the framing pyserial applied, once open
        details: dict[str, Any] = {
            "degraded_reason": reason,
            "port": port.state if port else "none",
            "address": self.config.get("port"),
            "baudrate": self.config.get("baudrate"),
            "framing": open_port.framing if open_port is not None else self.framing,
            "port_losses": port.losses if port else 0,
            "port_error": str(port.last_error) if port and port.state != "open" and port.last_error else "",
            "data": "none yet" if age is None else ("stale" if stale else "ok"),
            "last_data_age_s": "" if age is None else f"{age:.2f}",
            "stale_events": self.stale_events,
            "lines": self.lines,
            "published": self.published,
            "bad_checksums": sum(self.bad_checksums.values()),
            "bad_checksum_kinds": ",".join(f"{k}:{n}" for k, n in sorted(self.bad_checksums.items())),
            "malformed": self.malformed,
            "ignored": self.ignored,
            "noise_bytes": self.noise_bytes,
        }
        details.update(self.sensor_details())
        return details

    def publish_measurement(self, msg: t.StateInformation, *, received: float) -> bool:
        """Publish *msg* on STATE_INFO stamped with the time its first line arrived."""
        msg.header.timestamp_us = int(received * 1e6)
        ok = self.publish_state(msg)
        if ok:
            self.published += 1
        return ok

