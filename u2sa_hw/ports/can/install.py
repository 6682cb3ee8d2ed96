"""What install makes of a real SocketCAN address: the interface's bitrate, set by udev whenever it appears.

A real SocketCAN address with ``bitrate=`` gets a line that sets ``U2SA_CAN_BITRATE`` for that
interface, which ``70-u2sa-can.rules`` applies (``ip link set ... bitrate``, then up) at boot
and on replug (docs/deployment.md says why udev and not systemd-networkd). One interface has
one bitrate; one without ``bitrate=`` is left as configured (``u2sa check`` warns).
:func:`u2sa_hw.install.udev.plan_devices` calls :func:`plan_device` for each real CAN address,
then :func:`bitrate_rule` per interface.
"""

from __future__ import annotations

import re
from typing import TYPE_CHECKING, Any, Callable, Collection

if TYPE_CHECKING:
    from u2sa_hw.ports.address import DeviceAddress

_CAN = re.compile(r"^can[0-9]+$")
MAX_BITRATE = 8_000_000   # bit/s; CAN FD's data phase tops out here


def plan_device(plan: Any, name: str, address: DeviceAddress, *, service: str | None, elsewhere: Collection[str],
                fail: Callable[[str], Exception]) -> None:
    """Add to *plan* (a ``DevicePlan``) the bitrate of device *name*'s real SocketCAN interface."""
    if address.can_interface != "socketcan":
        return
    channel = address.can_channel
    if not _CAN.match(channel):
        raise fail(f"SocketCAN interface {channel!r}: install brings up only canN interfaces; rename it or bring "
                   "it up yourself")
    bitrate = address.bitrate
    if bitrate is None:
        plan.can_without_bitrate.append(f"{name} ({channel})")
        return
    if not 0 < bitrate <= MAX_BITRATE:
        raise fail(f"bitrate={bitrate} is not a CAN bitrate (bit/s, e.g. 500000)")
    if plan.can_channels.get(channel, bitrate) != bitrate:
        raise fail(f"{channel} at {bitrate} bit/s, but another device has it at {plan.can_channels[channel]}; "
                   "one interface has one bitrate")
    plan.can_channels[channel] = bitrate


def bitrate_rule(channel: str, bitrate: int) -> str:
    """The rule line that has ``70-u2sa-can.rules`` bring *channel* up at *bitrate*."""
    return f'SUBSYSTEM=="net", KERNEL=="{channel}", ENV{{U2SA_CAN_BITRATE}}="{bitrate}"'
