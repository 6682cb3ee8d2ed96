"""Surviving unplug and replug: a port that reopens itself with backoff.

A driver's loop asks ``ReconnectingPort.get()`` for the port each time round. While the
device is down, ``get()`` raises ``PortUnavailable`` at once (it never sleeps, so the
service keeps its heartbeat and health going); once the backoff window has passed it
calls the opener again. After a ``PortClosed``/``PortIOError`` the driver calls
``lost(exc)``. ``call(fn)`` does both for one operation.

Backoff (libbot2 procman's rule): the wait starts at ``initial_backoff`` and doubles after
every failed open and every loss, up to ``max_backoff``; it falls back to
``initial_backoff`` only when a port that was lost had stayed up for ``healthy_after``
seconds, so a device that opens and dies at once is not hammered.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable, Generic, TypeVar

from u2sa_hw.ports.errors import PortClosed, PortError, PortIOError, PortUnavailable

log = logging.getLogger(__name__)

P = TypeVar("P")
T = TypeVar("T")

OPEN = "open"
DOWN = "down"
CLOSED = "closed"


class ReconnectingPort(Generic[P]):
    """Holds the port *opener* returns, reopening it with backoff after a loss.

    ``state`` is "open", "down" (not open yet, lost or failing to open) or "closed"
    (after ``close()``); ``last_error`` is the latest PortError; ``losses`` counts ports
    lost while open and ``reopen_attempts`` counts calls of the opener after the first.
    Thread-safe: a reader and a writer thread may share one.
    """

    def __init__(self, opener: Callable[[], P], *, device: str, initial_backoff: float = 0.1,
                 max_backoff: float = 5.0, healthy_after: float = 10.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if initial_backoff <= 0 or max_backoff < initial_backoff:
            raise ValueError(f"{device}: need 0 < initial_backoff ({initial_backoff}) <= max_backoff ({max_backoff})")
        self.device = device
        self.initial_backoff = initial_backoff
        self.max_backoff = max_backoff
        self.healthy_after = healthy_after
        self._opener = opener
        self._clock = clock
        self._lock = threading.Lock()
        self._port: P | None = None
        self._state = DOWN
        self._delay = initial_backoff
        self._next_attempt: float | None = None  # None: try at once
        self._opened_at = 0.0
        self.last_error: PortError | None = None
        self.attempts = 0
        self.losses = 0

    @property
    def state(self) -> str:
        """One of "open", "down", "closed"."""
        return self._state

    @property
    def reopen_attempts(self) -> int:
        """How many times the opener was called after the first time."""
        return max(0, self.attempts - 1)

    @property
    def port(self) -> P | None:
        """The open port, or None while down."""
        return self._port

    def retry_in(self) -> float:
        """Seconds until ``get()`` will try the opener again (0 when open or due)."""
        with self._lock:
            if self._port is not None or self._next_attempt is None:
                return 0.0
            return max(0.0, self._next_attempt - self._clock())

    def _back_off(self, now: float) -> None:
        self._next_attempt = now + self._delay
        self._delay = min(self._delay * 2, self.max_backoff)

    def get(self) -> P:
        """The open port; opens it if due. Raises PortUnavailable while down (never sleeps),
        PortClosed after ``close()``. Errors other than PortError from the opener propagate."""
        with self._lock:
            if self._state == CLOSED:
                raise PortClosed(self.device, "closed by its owner", fix="create a new ReconnectingPort")
            if self._port is not None:
                return self._port
            now = self._clock()
            if self._next_attempt is not None and now < self._next_attempt - 1e-9:
                raise self._unavailable(f"down, next attempt in {self._next_attempt - now:.1f} s")
            self.attempts += 1
            try:
                port = self._opener()
            except PortError as exc:
                if self.last_error is None or str(exc) != str(self.last_error):
                    log.warning("%s: cannot open: %s", self.device, exc)
                self.last_error = exc
                self._back_off(now)
                if isinstance(exc, PortUnavailable):
                    raise
                raise self._unavailable("open failed") from exc
            if self.attempts > 1:
                log.info("%s: reopened after %d attempts", self.device, self.attempts)
            self._port = port
            self._state = OPEN
            self._opened_at = now
            return port

    def _unavailable(self, message: str) -> PortUnavailable:
        last = self.last_error
        if last is None:
            return PortUnavailable(self.device, message)
        text = str(last)
        if last.fix and text.endswith(f"; fix: {last.fix}"):
            text = text[: -len(f"; fix: {last.fix}")]
        return PortUnavailable(last.device, f"{message}; last error: {text}", address=last.address, fix=last.fix)

    def lost(self, exc: BaseException | None = None, *, port: P | None = None) -> None:
        """Mark the port down after *exc* (PortClosed/PortIOError) and close it.

        Pass the *port* the error came from when several threads share this object: a
        report about a port that was already replaced is then ignored.
        """
        with self._lock:
            current = self._port
            if current is None or (port is not None and port is not current):
                return
            self._port = None
            self._state = DOWN
            self.losses += 1
            if isinstance(exc, PortError):
                self.last_error = exc
            elif exc is not None:
                self.last_error = PortClosed(self.device, f"lost ({exc})")
            now = self._clock()
            if now - self._opened_at >= self.healthy_after:
                self._delay = self.initial_backoff
            self._back_off(now)
            log.warning("%s: lost (%s); reopening in %.1f s", self.device, exc, self._next_attempt - now)
        _close_quietly(current, self.device)

    def call(self, fn: Callable[[P], T]) -> T:
        """Run ``fn(port)``; on PortClosed/PortIOError mark the port lost and re-raise."""
        port = self.get()
        try:
            return fn(port)
        except (PortClosed, PortIOError) as exc:
            self.lost(exc, port=port)
            raise

    def close(self) -> None:
        """Close the port for good (idempotent)."""
        with self._lock:
            current, self._port = self._port, None
            self._state = CLOSED
        if current is not None:
            _close_quietly(current, self.device)

    def __repr__(self) -> str:
        return f"<ReconnectingPort {self.device} {self._state} losses={self.losses} attempts={self.attempts}>"


def _close_quietly(port: object, device: str) -> None:
    """Close a port that is being given up; its own errors no longer matter."""
    close = getattr(port, "close", None)
    if close is None:
        return
    try:
        close()
    except Exception as exc:  # noqa: BLE001 - the port is already dead; log and move on
        log.debug("%s: closing lost port: %s", device, exc)
