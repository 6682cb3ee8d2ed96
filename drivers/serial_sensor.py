"""The part every line-oriented serial sensor shares: the device link, counters, health.

:class:`SerialLineSensor` holds a :class:`~u2sa_hw.ports.device_link.DeviceLink` for its
device (``device`` setting, default the service name; its address, with the baud rate and
framing, is the profile's ``[devices.NAME] address``), so an unplugged device is reported in health and reopened with backoff while the service keeps
running. It reads whole lines and hands each to :meth:`handle_line`; when the line stays
quiet for ``epoch_gap_s`` it calls :meth:`handle_idle` (the end of a burst). With
``record_raw`` every chunk read is published as ``RawSerial`` on ``RAW.<device>``.

In a replay the port has a *device clock* (``mock+serial://...?clock=stamped``,
:mod:`u2sa_hw.ports.serial.clock`): a line's time is the recorded read time and a silence is
one of the recording, so the lines and silences the driver sees, and what it publishes, do
not depend on how fast or how loaded the replay is. A wall-clock read timeout then counts as
a silence only once the replay has sent nothing for ``DEVICE_CLOCK_GRACE_S`` (fail safe).

Its status is ``ok`` or ``degraded``; the reason (port down, no data, or the subclass's
:meth:`problem`, e.g. "no fix") is the ``degraded_reason`` health detail.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, ClassVar, Mapping

from u2sa_hw import lcmtypes as t
from u2sa_hw.abstract import ProprioceptiveSensor
from u2sa_hw.config.fields import ConfigError, field
from u2sa_hw.ports import PortClosed, PortIOError, PortUnavailable
from u2sa_hw.ports.declared import DeviceDeclarations
from u2sa_hw.ports.device_link import DeviceLink, device_setting
from u2sa_hw.ports.serial.port import SerialPort

_PORT_FIELDS = ("device", "device_name", "epoch_gap_s")


class SerialLineSensor(DeviceDeclarations, ProprioceptiveSensor):
    """A proprioceptive sensor that reads NMEA-style lines from one serial device."""

    CONFIG = (
        field("device", "", "the device: its [devices.NAME] table (address) and RAW.<device> "
                            "(empty: the service name)"),
        field("device_name", "", "old name of the device setting"),
        field("record_raw", False, "publish every chunk read as RawSerial on RAW.<device>"),
        field("stale_after_s", 2.0, "no valid sentence for this long -> degraded, data stale", gt=0, le=30.0),
        field("epoch_gap_s", 0.05, "this much silence on the line ends a burst of sentences (and is the read timeout)", gt=0, le=30.0),
    )
    EXAMPLE_PORT: ClassVar[str] = "/dev/u2sa/gps"

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self._link: DeviceLink[SerialPort] = DeviceLink(
            self, device=lambda: device_setting(self.config, self.name), raw_type=t.RawSerial,
            options=lambda: {"timeout": self.config.get("epoch_gap_s")})
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
        self._reopen = False
        self._problem = ""

    # -- config ------------------------------------------------------------------------------
    @classmethod
    def used_devices(cls, service: str, config: Mapping[str, Any]) -> tuple[str, ...]:
        """The one device this service reads (``device``, else the service's name)."""
        return (device_setting(config, service),)

    @classmethod
    def protocol(cls, config: Mapping[str, Any]) -> str:
        """What the device speaks (``nmea``; a compass: its ``format``)."""
        return "nmea"

    @classmethod
    def mock_wiring(cls, service: str, device: str, config: Mapping[str, Any]) -> dict[str, Any]:
        """What its mock mirrors: the protocol (u2sa_hw/ports/declared.py)."""
        return {"protocol": cls.protocol(config)}

    @classmethod
    def probe_expectation(cls, config: Mapping[str, Any]) -> dict[str, Any]:
        """The protocol the probe listens for (``NMEA``, ``OS5000``)."""
        return {"protocol": cls.protocol(config).upper()}

    @classmethod
    def replay_options(cls, device: str, config: Mapping[str, Any]) -> dict[str, Any]:
        """A replay groups the recorded reads into bursts by the driver's ``epoch_gap_s``."""
        return {"burst_gap_s": config.get("epoch_gap_s")}

    def check_config(self) -> None:
        """Refuse a device without an address (ConfigError names it and the fix); the fields' own rules
        (baud rates, framing, gaps) are declared on them. Offline (``u2sa check`` builds the driver without
        its link, and checks the device addresses itself) only the subclass's checks run."""
        link = getattr(self, "_link", None)
        problem = link.check() if link is not None else None
        if problem:
            raise ConfigError(f"service '{self.name}': {problem} (e.g. \"serial://{self.EXAMPLE_PORT}?baud=9600\")")

    @property
    def framing(self) -> str:
        """The framing as data bits, parity, stop bits (``8N1``, ``7E2``, ``8N1.5``) of the address ("" before
        the address is resolved)."""
        address = self._link.address
        return address.framing if address is not None else ""

    @property
    def device_name(self) -> str:
        """The device's name in port errors and taps (``device``, else the service name)."""
        return device_setting(self.config, self.name)

    def on_config_change(self, name: str, value: Any) -> None:
        """Check the new config; a device or gap change reopens the port (the address is re-read then)."""
        self.check_config()
        if name in _PORT_FIELDS:
            self._reopen = True
        if name == "record_raw" and value:
            self._link.record_changed()

    # -- port ----------------------------------------------------------------------------------
    def setup(self) -> None:
        """Resolve the device's address (the port is opened by the run loop)."""
        self._link.start()

    def run(self) -> None:
        """Read lines until stopped; survive port loss, bad bytes and silence."""
        link = self._link
        while self.wait(0.0):
            if self._reopen:
                self._reopen = False
                self.on_port_lost()
                link.refresh(force=True)
            try:
                port = link.get()
            except PortUnavailable:
                self.refresh_status()
                self.wait(min(0.5, max(0.02, link.retry_in())))
                continue
            except PortClosed:
                break  # closed by kill()
            try:
                line = port.readline()
            except (PortClosed, PortIOError) as exc:
                link.lost(exc, port=port)
                self.error(str(exc))
                self.on_port_lost()
                continue
            if line:
                self.lines += 1
                self._handle(line, received=line_time(port))
            elif port.went_quiet():   # a replay's device clock says whether the device fell silent
                self._idle()
            self.refresh_status()

    def _handle(self, line: bytes, *, received: float) -> None:
        try:
            self.handle_line(line, received)
        except Exception as exc:  # noqa: BLE001 - one unexpected line must not end the driver
            self.malformed += 1
            self.logger.exception("%s: line %r could not be handled: %s", self.name, line[:80], exc)

    def _idle(self) -> None:
        try:
            self.handle_idle()
        except Exception as exc:  # noqa: BLE001 - ending a burst must not end the driver either
            self.logger.exception("%s: ending a burst failed: %s", self.name, exc)

    def kill(self) -> None:
        """Close the port, then stop."""
        self._link.close()
        super().kill()

    # -- for subclasses ----------------------------------------------------------------------
    def handle_line(self, line: bytes, received: float) -> None:
        """One complete line from the device; *received* is the wall time (s) it was read (in a replay,
        the time the recorded driver read it: the port's device clock, see :func:`line_time`)."""
        raise NotImplementedError

    def handle_idle(self) -> None:
        """The line was quiet for ``epoch_gap_s`` (the end of a burst; in a replay, on the device clock)."""

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
        link = self._link
        age = self.data_age()
        limit = self.config.get("stale_after_s")
        if link.state not in ("open", "none"):
            reason = link.reason()
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
        link = self._link
        age = self.data_age()
        stale = age is None or age > self.config.get("stale_after_s")
        open_port = link.port  # the framing pyserial applied, once open
        address = link.address
        details: dict[str, Any] = {
            "degraded_reason": reason,
            **link.health(),
            "baudrate": address.baud if address is not None else "",
            "framing": open_port.framing if open_port is not None else self.framing,
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


def line_time(port: SerialPort) -> float:
    """When the line *port* just returned was read, in wall seconds: now, or for a port with a device
    clock (a replay's stamped pty) the recorded read time, so grouping by time does not depend on
    how fast the replay runs."""
    stamp = port.line_time_ns() if port.device_clock else None
    return time.time() if stamp is None else stamp / 1e9
