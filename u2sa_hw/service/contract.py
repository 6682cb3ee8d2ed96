"""The U2SA service contract (requirements C1-C9, thesis 8.2.3-8.2.4).

A service subclasses :class:`U2SAService`, declares its config fields in ``CONFIG``,
and writes ``setup()``, ``run()`` and ``callback()``. Everything else comes free:
configurator, logger, typed publish/subscribe, discovery, functionality discovery,
stop (all or by name), config enumeration and change over the bus, periodic health,
systemd notification (READY, WATCHDOG from the service's own loop, STATUS, STOPPING)
and clean exit on SIGTERM/SIGINT.

Config: fields are declared with :func:`~u2sa_hw.config.fields.field` (type, choices, bounds); the
one validation hook is :meth:`U2SAService.check_config`, for what a single field cannot say.

A run loop is written as ``while self.wait(period): ...``: ``wait`` returns False once
the service is stopping and pings systemd's watchdog (every half ``$WATCHDOG_USEC``, however
long the period), so a hung loop is a dead service but a slow one is not.

Log level: ``u2sa service --log-level`` at start, else the service's ``log_level`` config
field (its TOML file or the profile's settings for it), else the profile's ``log_level``,
else info. A change of ``log_level`` over the bus applies at once (empty: the profile's).
"""

from __future__ import annotations

import gc
import logging
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any, Callable, ClassVar

from u2sa_hw import channels as ch
from u2sa_hw.config.configurator import Configurator
from u2sa_hw.config.fields import ConfigError, ConfigField
from u2sa_hw.bus.threads import name_native_thread
from u2sa_hw.service.health import ProcessStats, build_health
from u2sa_hw.messages import type_name
from u2sa_hw.service.sdnotify import SystemdNotifier, watchdog_interval
from u2sa_hw.service.bus_handlers import DUPLICATE_EXIT, DuplicateWatch, bus_text, listen_state, raises_text, rejected_text
from u2sa_hw.service.base_config import BASE_CONFIG
from u2sa_hw.service.contract_requests import ContractRequests
from u2sa_hw.service.log import level_number, set_level
from u2sa_hw.bus.client import root_header
from u2sa_hw.bus.transport import Transport
from u2sa_hw.profile.vehicle import VehicleProfile

def settle_memory() -> None:
    """After start-up: collect once, then freeze what is left out of the collector's sight.

    Everything alive now (modules, the profile, the service's tables) lives as long as the
    process; frozen, the cyclic collector no longer walks it on every full collection, which
    on a small board is a pause of several ms in the middle of a control loop.
    """
    gc.collect()
    gc.freeze()


class U2SAService(ContractRequests):
    """Base of every service: the contract; subclasses write setup/run/callback."""

    SERVICE_TYPE: ClassVar[str] = "service"
    CONFIG: ClassVar[tuple[ConfigField, ...]] = ()

    def __init__(self, name: str, *, profile: VehicleProfile | None = None, config_path: Path | str | None = None,
                 settings: dict[str, Any] | None = None, transport: Transport | None = None,
                 logger: logging.Logger | None = None) -> None:
        self.name = name
        self.profile = profile or VehicleProfile(path=None)
        self.logger = logger or logging.getLogger(f"u2sa.{name}")
        path = config_path if config_path is not None else self.profile.config_path_for(name)
        where = f"{self.profile.path} [services.{name}] settings" if self.profile.path else f"service '{name}' settings"
        self.config = Configurator(path, (*BASE_CONFIG, *self.config_fields()), logger=self.logger, initial=settings,
                                   initial_source=where, validator=self.validate_config)
        self.transport = transport or Transport(self.profile.lcm_url, name=name,
                                                security=self.profile.bus_security, key_file=self.profile.bus_key,
                                                interface=self.profile.bus_interface,
                                                system_id=self.profile.system_id, vehicle=True)
        self.running = False
        self.status = "starting"
        self.last_error = ""
        self.thread_id = threading.get_ident()
        self._stop_event = threading.Event()
        self._publishers: dict[str, str] = {}     # channel -> type name (functionality discovery)
        self._subscribers: dict[str, str] = {}
        self._subscriptions: dict[str, list[Any]] = {}   # channel -> transport subscriptions
        self._unhandled: dict[str, int] = {}      # message type -> count reaching the default callback
        self._sequence: dict[str, int] = {}
        self._stats = ProcessStats()
        self._notifier = SystemdNotifier()
        self._watchdog_period = watchdog_interval()
        self._last_watchdog = 0.0
        self._last_loop = time.monotonic()
        self._health_thread: threading.Thread | None = None
        self._bus_listen = ""   # where the bus listens when not where it belongs (set by start())
        self._duplicates = DuplicateWatch(self)   # another of this name on the bus: refuse, or the newer stops
        self._contract_subscriptions()

    @classmethod
    def config_fields(cls) -> list[ConfigField]:
        """Every declared field: each class's own ``CONFIG`` along the MRO, base classes first."""
        seen: dict[str, ConfigField] = {}
        for klass in reversed(cls.__mro__):
            for f in klass.__dict__.get("CONFIG", ()):
                seen[f.name] = f
        return list(seen.values())

    # -- thesis contract: implementation provided ----------------------------------------
    def get_service_name(self) -> str:
        """The service's unique name."""
        return self.name

    def is_running(self) -> bool:
        """True while the service loops."""
        return self.running

    def get_thread_id(self) -> int:
        """The id of the thread that runs the service."""
        return self.thread_id

    def log(self, message: str, level: str = "info") -> None:
        """Write *message* to the service's log at *level* (debug, info, warn, error)."""
        self.logger.log(level_number(level), message)

    def register_publisher(self, channel: str, msg_type: type) -> None:
        """Declare that this service publishes *msg_type* on *channel* (for discovery)."""
        self._publishers[channel] = type_name(msg_type)

    def unregister_publisher(self, channel: str) -> None:
        """Withdraw *channel* from the published channels in discovery (publishing on it again re-declares it)."""
        self._publishers.pop(channel, None)

    def register_subscriber(self, channel: str, msg_type: type,
                            callback: Callable[[Any], None] | None = None) -> None:
        """Subscribe to *channel* as *msg_type* (its base type); messages go to *callback* or ``callback()``."""
        self._subscribers[channel] = type_name(msg_type)
        target = callback or self.callback
        sub = self.transport.subscribe(channel, msg_type, lambda _ch, msg: target(msg))
        self._subscriptions.setdefault(channel, []).append(sub)

    def unregister_subscriber(self, channel: str) -> None:
        """Unsubscribe every handler this service registered on *channel* and drop it from discovery."""
        self._subscribers.pop(channel, None)
        for sub in self._subscriptions.pop(channel, []):
            self.transport.unsubscribe(sub)

    def publish(self, channel: str, msg: Any, *, restamp: bool = False) -> bool:
        """Stamp *msg*'s header (system id, source, sequence, time) and publish it; True on success.

        A timestamp the caller already set is kept: it is the time of the measurement (a driver
        stamps when the bytes arrived, the pass-through estimator forwards its sensor's), not of
        sending. A zero timestamp, or any with ``restamp=True``, becomes now.
        """
        header = root_header(msg)
        if header is not None:
            seq = self._sequence.get(channel, 0) + 1
            self._sequence[channel] = seq
            header.system_id = self.profile.system_id
            if restamp or not header.timestamp_us:
                header.timestamp_us = time.time_ns() // 1000
            header.source = self.name
            header.sequence = seq
        if channel not in self._publishers:
            self._publishers[channel] = type_name(msg)
        return self.transport.publish(channel, msg)

    # -- thesis contract: for subclasses --------------------------------------------------
    def setup(self) -> None:
        """Open resources and register publishers/subscribers (before READY)."""

    def run(self) -> None:
        """Continuous work; loops while running. The default only waits for a stop."""
        while self.wait(1.0):
            pass

    def callback(self, data: Any) -> None:
        """Handle a message from a subscription; the default counts it as unhandled (a warning per type)."""
        kind = type(data).__name__
        count = self._unhandled.get(kind, 0)
        self._unhandled[kind] = count + 1
        if count == 0:
            self.logger.warning("unhandled message type %s reached %s.callback(); further ones are counted "
                                "in health (unhandled)", kind, type(self).__name__)

    def kill(self) -> None:
        """Stop looping and release resources (subclasses close theirs, then call this)."""
        self.running = False
        self._stop_event.set()

    def health_details(self) -> dict[str, Any]:
        """Service-specific key/values for the health message (override)."""
        return {}

    def check_config(self) -> None:
        """THE validation hook: raise ConfigError (or ValueError) naming the field and the fix when the
        config, as ``self.config`` reads it, cannot work (override; call ``super().check_config()``).

        Each field's own rules -- type, ``choices``, bounds (``ge``/``gt``/``le``/``lt``), finite
        numbers, ``remote`` -- are declared on :func:`~u2sa_hw.config.fields.field` and checked before
        this, for the file, the profile's settings and every change over the bus. This hook is for
        what one field cannot say: a combination (one wheel radius per actuator), a value a
        device must support (a baud rate), text to parse (a line map). The base calls it:

        - in :meth:`start`, before ``setup()``: a file that cannot work stops the service with
          the reason before it touches a device (a service may also call it in ``__init__``);
        - before every change over the bus (``ConfigChange``, ``u2sa param set``), with the
          proposed value in place (:meth:`Configurator.trial`): a refused value never reaches
          the file, and the requester gets the reason.

        It must not change the service's state: it may run with a value that is then refused.
        """

    def validate_config(self, name: str, value: Any) -> str | None:
        """Why changing *name* to *value* (already of the field's type and range) is refused, or None.

        Not a hook (override :meth:`check_config`): a field declared ``remote=False`` is not changed
        over the bus, and :meth:`check_config` runs with the value tried in place.
        """
        f = self.config.fields.get(name)
        if f is not None and not f.remote and value != self.config.get(name):
            return (f"service '{self.name}': {name} is not changed over the bus ({f.help}); set it in the "
                    "profile and restart the service")
        with self.config.trial(name, value):
            try:
                self.check_config()
            except (ConfigError, ValueError) as exc:
                return str(exc)
        return None

    def on_config_change(self, name: str, value: Any) -> None:
        """Called after a config field changed over the bus (override to apply it live)."""

    def log_level_name(self) -> str:
        """The level this service logs at: its ``log_level`` field, else the profile's, else info."""
        return self.config.get("log_level") or self.profile.log_level or "info"

    # -- loop helpers ---------------------------------------------------------------------
    def wait(self, timeout: float) -> bool:
        """Sleep up to *timeout* s (less if stopped); ping the watchdog; False once stopping.

        Under a systemd watchdog the sleep is cut in slices of a quarter of ``$WATCHDOG_USEC``
        and a ping goes out every half, so a period longer than ``WatchdogSec`` is no hang.
        """
        now = self._last_loop = time.monotonic()
        deadline = now + max(0.0, timeout)
        while True:
            self._ping_watchdog()
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            if self._watchdog_period is not None:
                remaining = min(remaining, self._watchdog_period / 2)
            if self._stop_event.wait(remaining):
                return False
        return self.running and not self._stop_event.is_set()

    def _ping_watchdog(self) -> None:
        if self._watchdog_period is None:
            return
        now = time.monotonic()
        if now - self._last_watchdog >= self._watchdog_period:
            self._last_watchdog = now
            self._notifier.notify("WATCHDOG=1")

    def _ping_while_stopping(self) -> threading.Event:
        """Ping the watchdog every half period from a thread of its own until the returned event is set."""
        done = threading.Event()
        if self._watchdog_period is not None:
            period = self._watchdog_period

            def ping() -> None:
                while not done.wait(period):
                    self._notifier.notify("WATCHDOG=1")

            threading.Thread(target=ping, name=f"stopping-{self.name}", daemon=True).start()
        return done

    def notify_status(self, text: str) -> None:
        """Set systemd's STATUS= line for this unit."""
        self._notifier.notify(f"STATUS={text}")

    def error(self, text: str) -> None:
        """Record *text* as the last error (shown in health) and log it."""
        self.last_error = text
        self.logger.error(text)

    # -- health ----------------------------------------------------------------------------
    def _health_loop(self) -> None:
        while not self._stop_event.wait(max(0.05, float(self.config.get("health_interval_s")))):
            self.publish_health()

    def publish_health(self) -> None:
        """Publish one Health message now."""
        try:
            details = {"loop_age_s": f"{time.monotonic() - self._last_loop:.2f}", **self.health_details()}
            if self._unhandled:
                details["unhandled"] = ",".join(f"{k}:{n}" for k, n in sorted(dict(self._unhandled).items()))
        except Exception as exc:  # noqa: BLE001 - health must still go out
            details = {"health_details_error": str(exc)}
        details["bus_security"] = bus_text(self.transport)
        details.update(self._duplicates.details())   # started_us, stack_pid: which of two of this name is newer
        rejected = rejected_text(self.transport.rejected())
        if rejected:
            details["bus_rejected"] = rejected
        raises = self.transport.accepted_raise_log()   # usually empty: nothing to format
        if raises:   # failsafe raises let through though stale or foreign (they fail safe): who and when
            details["bus_raises_accepted"] = raises_text(raises)
        listen = self._bus_listen or self.transport.listen_problem   # u2sa_hw.service.bus_handlers.listen_state
        if listen:   # a ttl=0 bus heard beyond this board, a ttl>=1 one on the default route
            details["bus_listen"] = listen
        last_error = self.last_error or self.transport.last_error
        msg = build_health(name=self.name, service_type=self.SERVICE_TYPE, status=self.status, stats=self._stats,
                           transport=self.transport, last_error=last_error, details=details)
        self.publish(ch.HEALTH, msg)

    # -- lifecycle -------------------------------------------------------------------------
    def start(self) -> None:
        """Set up, start the transport and health, mark running, tell systemd READY."""
        self.running = True
        self._bus_listen = listen_state(self)
        if self._bus_listen and not self.transport.listen_problem:   # listen_problem was logged as it was found
            self.logger.warning("%s", self._bus_listen)
        self.check_config()
        self.setup()
        self.transport.start()
        self.status = "ok" if self.status == "starting" else self.status
        self._health_thread = threading.Thread(target=self._health_loop, name=f"health-{self.name}", daemon=True)
        self._health_thread.start()
        name_native_thread(self._health_thread, f"health {self.name}")
        self.publish_health()
        self._notifier.notify("READY=1")
        self.notify_status(f"{self.name} ({self.SERVICE_TYPE}) running")
        self.logger.info("%s (%s) started, pid %d, LCM %s, bus %s", self.name, self.SERVICE_TYPE, os.getpid(),
                         self.transport.url, bus_text(self.transport))
        if self.transport.auth is None:
            self.logger.warning("the bus is open (bus_security = \"open\"): messages are neither signed nor "
                                "verified, any process that reaches the multicast group can command this vehicle")

    def stop(self) -> None:
        """Ask the service to stop (from any thread or a signal handler)."""
        self.running = False
        self._stop_event.set()

    def main(self, *, log_level: str | None = None) -> int:
        """Run the service in the foreground until stopped; return the exit status (0 when clean).

        The process logs at *log_level* (the command line's), else :meth:`log_level_name`.
        """
        set_level(log_level or self.log_level_name())
        self.thread_id = threading.get_ident()
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: self.stop())
        other = self._duplicates.probe()
        if other is not None:   # before setup(): no device opened, no health published
            self.logger.error("%s", other)
            self.transport.stop()
            self._notifier.close()
            return DUPLICATE_EXIT
        code = 0
        try:
            self.start()
            self._duplicates.arm()   # for a while, the newer of two of this name (started together) stops
            settle_memory()
            self.run()
        except Exception as exc:  # noqa: BLE001 - log the reason before dying with non-zero
            self.logger.exception("%s failed: %s", self.name, exc)
            code = 1
        finally:
            self.status = "stopping"
            # The stop's acknowledgement: the launcher (u2sa run) then waits for the exit, and while the
            # shutdown below runs (kill(), the transport, the bus clock's fsync) a thread keeps pinging the
            # watchdog, so a slow shutdown on a loaded machine is not taken for a hung one (docs/supervision.md).
            self._notifier.notify("STOPPING=1")
            pinging = self._ping_while_stopping()
            try:
                self.publish_health()
            except Exception:  # noqa: BLE001 - best effort on the way out
                pass
            try:
                self.kill()
            except Exception as exc:  # noqa: BLE001
                self.logger.error("kill() of %s failed: %s", self.name, exc)
                code = code or 1
            self._duplicates.close()
            self.transport.stop()
            pinging.set()   # done: what is left (the interpreter's exit) shows progress as CPU time
            self._notifier.close()
            self.logger.info("%s stopped", self.name)
        return DUPLICATE_EXIT if self._duplicates.refusal is not None else code
