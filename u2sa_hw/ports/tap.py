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
