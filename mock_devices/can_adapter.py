"""A CAN adapter that can be unplugged: a python-can interface for losing the bus itself.

``UnpluggableCanBus`` is a python-can bus (interface name ``"u2sa_unpluggable"`` once
:func:`register` has run in the process) that passes frames to and from python-can's
``virtual`` bus of the same channel, so mock nodes on ``virtual`` and a driver on this
interface meet as usual. :func:`unplug` pulls the adapter out, the way a USB-CAN adapter
disappears or ``ip link set can0 down`` takes SocketCAN away: every open bus on the channel
fails its next send and receive with ``ENETDOWN`` and opening one fails with ``ENODEV``
(the errnos SocketCAN gives), until :func:`replug`.

It exists in one process only (python-can finds it through ``can.interfaces.BACKENDS``),
so a test runs the driver in the test process, on a thread.
"""

from __future__ import annotations

import errno
import threading
from typing import Any

import can
import can.util
from can.interfaces.virtual import VirtualBus

INTERFACE = "u2sa_unpluggable"

_lock = threading.Lock()
_unplugged: set[str] = set()


def register() -> str:
    """Make the interface known to python-can in this process; returns its name.

    This is what python-can does at import for the ``can.interface`` entry points: add the
    backend to ``BACKENDS`` and its name to the set of valid interfaces ``can.Bus`` checks.
    """
    can.interfaces.BACKENDS[INTERFACE] = (__name__, "UnpluggableCanBus")
    can.util.VALID_INTERFACES = can.util.VALID_INTERFACES | {INTERFACE}
    return INTERFACE


def unplug(channel: str) -> None:
    """Pull the adapter of *channel* out: buses on it fail (ENETDOWN), opening fails (ENODEV)."""
    with _lock:
        _unplugged.add(channel)


def replug(channel: str) -> None:
    """Plug the adapter of *channel* back in: it can be opened again (open buses stay dead)."""
    with _lock:
        _unplugged.discard(channel)


def is_plugged(channel: str) -> bool:
    """False between :func:`unplug` and :func:`replug` of *channel*."""
    with _lock:
        return channel not in _unplugged


class UnpluggableCanBus(can.BusABC):
    """A bus on python-can's ``virtual`` *channel* that dies when its adapter is unplugged."""

    def __init__(self, channel: str, **kwargs: Any) -> None:
        if not is_plugged(channel):
            raise can.CanInitializationError(f"no CAN adapter for {channel!r} (unplugged)", error_code=errno.ENODEV)
        self._inner = VirtualBus(channel=channel, **kwargs)
        self._dead = False
        self.channel_info = f"unpluggable adapter on virtual channel {channel!r}"
        self._channel = channel
        super().__init__(channel=channel, **kwargs)

    def _check_plugged(self) -> None:
        if self._dead or not is_plugged(self._channel):
            self._dead = True  # like a real adapter: once gone, this handle stays gone
            raise can.CanOperationError("Network is down (adapter unplugged)", error_code=errno.ENETDOWN)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send *msg* on the virtual channel, or fail with ENETDOWN once unplugged."""
        self._check_plugged()
        self._inner.send(msg, timeout=timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        self._check_plugged()
        msg = self._inner.recv(timeout)
        self._check_plugged()  # unplugged while waiting
        return msg, False

    def shutdown(self) -> None:
        """Release the virtual bus."""
        super().shutdown()
        self._inner.shutdown()
