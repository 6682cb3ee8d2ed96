"""The one table of port kinds: address kind -> :class:`~u2sa_hw.ports.port_kind.PortKind`.

Each kind lives in its package, ``u2sa_hw/ports/<kind>/`` (grammar, backends, mock client,
wire protocol); a new kind is one folder and one line here. The address parser, ``open_port``,
``preload`` and the docs' scheme table all read this table; ``tests/test_port_kinds.py`` checks
that every kind has every part.
"""

from __future__ import annotations

from types import MappingProxyType
from typing import Mapping

from u2sa_hw.ports.can.kind import CAN
from u2sa_hw.ports.gpio.kind import GPIO
from u2sa_hw.ports.i2c.kind import I2C
from u2sa_hw.ports.port_kind import PortKind
from u2sa_hw.ports.pwm.kind import PCA9685, PWM
from u2sa_hw.ports.serial.kind import SERIAL

PORT_KINDS: Mapping[str, PortKind] = MappingProxyType({kind.name: kind for kind in (SERIAL, CAN, I2C, GPIO, PWM,
                                                                                      PCA9685)})


def port_kind(name: str) -> PortKind:
    """The kind named *name* (``DeviceAddress.kind``); KeyError names the known ones."""
    try:
        return PORT_KINDS[name]
    except KeyError:
        raise KeyError(f"no port kind {name!r}; known: {', '.join(PORT_KINDS)}") from None
