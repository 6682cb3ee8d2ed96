"""One device's lifecycle, held by a driver (composition, not a base class).

A :class:`DeviceLink` owns what every driver family used to wire by itself:

- **the address**: ``[devices.NAME] address`` of the vehicle profile
  (:func:`u2sa_hw.profile.devices.device_address`);
- **open** through :func:`~u2sa_hw.ports.opener.open_port`, then the driver's ``on_open``
  (chip init, reading the present levels); a PortError there counts as a failed open;
- **reconnect with backoff** (:class:`~u2sa_hw.ports.reconnect.ReconnectingPort`): ``get()``
  never sleeps, so the service's heartbeat and health go on while the device is away;
- **the tap**: every raw record is published on ``RAW.<device>`` (the one naming rule,
  :func:`~u2sa_hw.ports.tap.raw_channel`) while the owner's ``record_raw`` is on;
- **reopen on an address change**: ``refresh()`` re-resolves the device and its address and
  reopens when either changed (or when asked to, e.g. after a framing change); an actuator's
  ``before_close`` hook runs first on the old, still open port, so the controllers there get
  their neutral/idle before the driver lets go of them (fail safe: they would otherwise hold
  their last setpoint until their own watchdog, if any, fires);
- **an address a port refuses** (a GPIO line the address does not list): an ``AddressError``
  from the opener is a failed open (``PortUnavailable`` with the fix) in health, never an
  exception out of the driver's loop;
- **port health**: :meth:`health` gives ``port`` (open/down/closed), ``address``,
  ``port_error`` (the last error with its fix), ``port_losses`` and ``reconnects``, which the
  driver puts into its Health, so ``u2sa health`` shows why a device is down.

A driver declares the devices it uses for the rest of the system with a classmethod::

    @classmethod
    def used_devices(cls, service: str, config: Mapping[str, Any]) -> tuple[str, ...]:
        # the names of the profile devices the service uses (u2sa_hw.ports.declared)

which :func:`u2sa_hw.profile.devices.profile_devices` calls; the driver's own setting names stay in
the driver.
"""

from __future__ import annotations

import logging
from typing import Any, Callable, Generic, Mapping, TypeVar

from u2sa_hw.ports.address import AddressError, DeviceAddress
from u2sa_hw.ports.errors import PortError, PortUnavailable
from u2sa_hw.ports.opener import open_port, preload
from u2sa_hw.ports.reconnect import ReconnectingPort
from u2sa_hw.ports.tap import RecordingTap, raw_channel

log = logging.getLogger(__name__)

P = TypeVar("P")
T = TypeVar("T")


def device_setting(config: Mapping[str, Any], service: str) -> str:
    """The device a single-device driver uses: its ``device`` setting, else the old
    ``device_name``, else the service's name."""
    for key in ("device", "device_name"):
        try:
            value = config.get(key)
        except KeyError:   # a Configurator without the field
            continue
        if isinstance(value, str) and value.strip():
            return value.strip()
    return service


class DeviceLink(Generic[P]):
    """The open/reconnect/tap/health lifecycle of one device for the driver *owner*.

    *owner* is the service (``profile``, ``config``, ``publish``, ``register_publisher``);
    *device* is called on each (re)resolve: the device's name. *options* returns ``open_port``'s keyword
    options (read timeout, GPIO lines, PWM period). *before_close* is called with the open port
    before ``refresh()`` closes it for a reopen (an actuator writes its neutral/idle there; its
    errors are logged, never stop the reopen). *raw_type* is the LCM type (or types) of
    the records the port hands its tap; *record* says whether to publish them (default: the owner's
    ``record_raw`` setting).
    """

    def __init__(self, owner: Any, *, device: Callable[[], str], raw_type: type | tuple[type, ...],
                 options: Callable[[], Mapping[str, Any]] | None = None,
                 on_open: Callable[[P], None] | None = None, record: Callable[[], bool] | None = None,
                 before_close: Callable[[P], None] | None = None,
                 initial_backoff: float = 0.1, max_backoff: float = 5.0, healthy_after: float = 10.0) -> None:
        self.owner = owner
        self._device_of = device
        self._options = options or (lambda: {})
        self._on_open = on_open
        self._before_close = before_close
        self._record = record or (lambda: bool(owner.config.get("record_raw")))
        # the port's tap (and the one a second port of the same device, an MPU-9250's magnetometer, hands its
        # records to): publishes on RAW.<device> while recording is on; a port builds no record while it is off
        self.tap = RecordingTap(self._publish_raw, active=self._record)
        self.raw_type = raw_type
        self._backoff = dict(initial_backoff=initial_backoff, max_backoff=max_backoff, healthy_after=healthy_after)
        self.device = device()
        self.address: DeviceAddress | None = None
        self._holder: ReconnectingPort[P] | None = None
        self.total_losses = 0     # across reopens on an address change
        self.total_reconnects = 0
        self._registered: set[str] = set()

    # ---- the address -----------------------------------------------------------------------------
    def resolve(self) -> DeviceAddress:
        """The device's address now (AddressError names the device and the fix when there is none)."""
        from u2sa_hw.profile.devices import device_address

        device = self._device_of()
        return device_address(self.owner.profile, device)

    def check(self) -> str | None:
        """Why the device cannot be opened as configured (a bad or missing address), or None."""
        try:
            self.resolve()
        except AddressError as exc:
            return str(exc)
        return None

    # ---- lifecycle -------------------------------------------------------------------------------
    def start(self) -> None:
        """Resolve the address and create the reconnecting port (opened by the first ``get()``).

        What the open will import is imported now (``opener.preload``): the driver calls this in
        ``setup()``, before READY=1 arms its watchdog, and the first open runs in its loop.
        """
        self.device = self._device_of()
        self.address = self.resolve()
        preload(self.address)
        self.record_changed()
        self._holder = ReconnectingPort(self._open, device=self.device, **self._backoff)

    def refresh(self, *, force: bool = False) -> bool:
        """Re-resolve device and address; reopen when they changed or *force*. True when reopened."""
        device, address = self._device_of(), self.resolve()
        if not force and self._holder is not None and device == self.device and address == self.address:
            return False
        old = self._holder
        if old is not None:
            self._park(old)
            self.total_losses += old.losses
            self.total_reconnects += old.reopen_attempts
            old.close()
        if address != self.address or device != self.device:
            log.info("%s: device %s at %s", self.owner.name if hasattr(self.owner, "name") else "?", device, address)
        self.device, self.address = device, address
        self.record_changed()
        self._holder = ReconnectingPort(self._open, device=self.device, **self._backoff)
        return True

    def record_changed(self) -> None:
        """Declare the ``RAW.<device>`` publisher once recording is on."""
        channel = raw_channel(self.device)
        if self._record() and channel not in self._registered:
            for raw_type in self.raw_type if isinstance(self.raw_type, tuple) else (self.raw_type,):
                self.owner.register_publisher(channel, raw_type)
            self._registered.add(channel)

    def _park(self, holder: ReconnectingPort[P]) -> None:
        """Before a reopen: the driver's ``before_close`` on the old port while it is still open."""
        port = holder.port if holder.state == "open" else None
        if self._before_close is None or port is None:
            return
        try:
            self._before_close(port)
        except Exception as exc:  # noqa: BLE001 - the reopen goes on; the old port may already be failing
            log.warning("%s: neutral on the old port before the reopen failed: %s", self.device, exc)

    def _open(self) -> P:
        assert self.address is not None, "start() resolves the address"
        try:
            port = open_port(self.address, device=self.device, tap=self.tap, **dict(self._options()))
        except AddressError as exc:   # e.g. a GPIO line the address does not list: a port fault, with the fix
            raise PortUnavailable(self.device, exc.problem, address=self.address.url, fix=exc.fix) from None
        if self._on_open is not None:
            try:
                self._on_open(port)
            except BaseException:   # a PortError counts as a failed open; anything else propagates
                _close_quietly(port)
                raise
        return port

    def _publish_raw(self, record: Any) -> None:
        self.owner.publish(raw_channel(self.device), record)

    @property
    def holder(self) -> ReconnectingPort[P]:
        """The reconnecting port (after ``start()``)."""
        assert self._holder is not None, "start() creates the port"
        return self._holder

    def get(self) -> P:
        """The open port; opens it when due. PortUnavailable while down, PortClosed after ``close()``."""
        return self.holder.get()

    def call(self, fn: Callable[[P], T]) -> T:
        """``fn(port)``; a PortClosed/PortIOError marks the port lost and is re-raised."""
        return self.holder.call(fn)

    def lost(self, exc: BaseException | None = None, *, port: P | None = None) -> None:
        """The port failed: close it and reopen with backoff."""
        if self._holder is not None:
            self._holder.lost(exc, port=port)

    def retry_in(self) -> float:
        """Seconds until the next open attempt (0 when open)."""
        return self._holder.retry_in() if self._holder is not None else 0.0

    def close(self) -> None:
        """Close for good (idempotent)."""
        if self._holder is not None:
            self._holder.close()

    @property
    def state(self) -> str:
        """``open``, ``down``, ``closed`` or ``none`` (before ``start()``)."""
        return self._holder.state if self._holder is not None else "none"

    @property
    def port(self) -> P | None:
        """The open port, or None."""
        return self._holder.port if self._holder is not None else None

    @property
    def losses(self) -> int:
        """Ports lost while open, over the link's life."""
        return self.total_losses + (self._holder.losses if self._holder is not None else 0)

    @property
    def last_error(self) -> PortError | None:
        """The latest port error (with its fix)."""
        return self._holder.last_error if self._holder is not None else None

    def health(self) -> dict[str, Any]:
        """Port state, address, the last error with its fix (while not open), losses and reconnects."""
        holder = self._holder
        error = holder.last_error if holder is not None else None
        return {
            "device": self.device,
            "port": self.state,
            "address": self.address.url if self.address is not None else "",
            "port_error": str(error) if error is not None and self.state != "open" else "",
            "port_losses": self.losses,
            "reconnects": self.total_reconnects + (holder.reopen_attempts if holder is not None else 0),
        }

    def reason(self) -> str:
        """``"port down"``/``"port closed"`` for a degraded status while not open, else ``""``
        (the error with its fix is the ``port_error`` health detail)."""
        if self.state == "open" or self._holder is None:
            return ""
        return f"port {self.state}"


def _close_quietly(port: object) -> None:
    close = getattr(port, "close", None)
    if close is not None:
        try:
            close()
        except Exception as exc:  # noqa: BLE001 - the port failed its init; its close errors do not matter
            log.debug("closing a port whose init failed: %s", exc)
