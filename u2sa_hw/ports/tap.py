"""Port taps: every byte, frame, register transaction, edge and PWM write that crosses a
port can be handed to a tap, which the service publishes as ``RAW.<device>`` messages
(the raw device I/O types in ``u2sa_hw.lcmtypes``) when recording is on.

A tap is any callable taking one raw LCM message (``RawSerial``, ``RawCanFrame``,
``RawI2c``, ``RawGpioEdge``, ``RawGpioWrite``, ``RawPwmWrite``). Ports fill ``device``,
``direction`` and the payload; the tap's owner stamps the header when publishing.
"""

from __future__ import annotations

from typing import Any, Callable

Tap = Callable[[Any], None]

RX = 0  # from the device: bytes read, frames received, register reads, edges
TX = 1  # to the device: bytes written, frames sent, register writes, output writes


class RecordingTap:
    """A tap that knows whether it records now: ``active()``. Every port (serial, CAN, I2C, GPIO, PWM) asks
    :func:`tapping` before it builds a record, so a driver with recording off builds none (a record per
    frame, byte or edge costs more than reading it)."""

    __slots__ = ("_publish", "active")

    def __init__(self, publish: Callable[[Any], None], *, active: Callable[[], bool]) -> None:
        self._publish = publish
        self.active = active

    def __call__(self, record: Any) -> None:
        if self.active():
            self._publish(record)


def tapping(tap: Tap | None) -> bool:
    """Whether a record for *tap* is worth building: there is a tap and, if it says (``active``), it records."""
    if tap is None:
        return False
    active = getattr(tap, "active", None)
    return active is None or bool(active())


def raw_channel(device: str) -> str:
    """The LCM channel that carries the raw I/O of *device*."""
    return f"RAW.{device}"


def call_tap(tap: Tap | None, record: Any) -> None:
    """Hand *record* to *tap* if there is one; a failing tap never breaks the port."""
    if tap is None:
        return
    try:
        tap(record)
    except Exception:  # noqa: BLE001 - a recording problem must not stop the device I/O
        import logging

        logging.getLogger("u2sa_hw.ports").exception("port tap failed")
