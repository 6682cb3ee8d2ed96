"""Replay devices for the buses: the I2C bus (:mod:`u2sa_hw.hil.replay_i2c`: chips answering with recorded
register reads, data reads paced by the player), and CAN frames sent onto a private UDP multicast bus
(:class:`~u2sa_hw.ports.can.replay.ReplayCanDevice`, in its kind's package: it needs nothing from
``hil``). Serial is in :mod:`u2sa_hw.ports.serial.replay`; the interface is the same.

:func:`make_device` makes a device of any kind through the port kind table: each kind's ``replay`` part
(:data:`u2sa_hw.ports.kinds.PORT_KINDS`) names its factory, ``make_<kind>_device`` here (GPIO and PWM
hand on to :mod:`u2sa_hw.hil.replay_gpio`) or ``make_serial_device`` in :mod:`u2sa_hw.hil.replay_devices`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from u2sa_hw.bus.udp_ports import private_udp_port
from u2sa_hw.ports.can.replay import (CAN_BACKLOG_BYTES, CAN_CHECK_EVERY, CAN_GROUP, ReplayCanDevice, socket_inodes,
                                      udp_backlog)

from u2sa_hw.hil.replay_i2c import I2C_BACKLOG_READS, I2C_CLIENT_TIMEOUT_S, ReplayI2cChip, ReplayI2cDevice
from u2sa_hw.hil.replay_plan import DevicePlan, ReplayError, ServicePlan

__all__ = ["CAN_BACKLOG_BYTES", "CAN_CHECK_EVERY", "CAN_GROUP", "I2C_BACKLOG_READS", "I2C_CLIENT_TIMEOUT_S",
           "ReplayCanDevice", "ReplayI2cChip", "ReplayI2cDevice", "make_can_device", "make_device", "make_gpio_device",
           "make_i2c_device", "make_pwm_device", "socket_inodes", "udp_backlog"]


def make_device(dev: DevicePlan, run_dir: Path, service: ServicePlan, *, fast: bool,
                rigs: dict[str, Any] | None = None) -> Any:
    """The replay device for *dev*, driven by *service*: the factory its port kind's ``replay`` part
    names (:data:`u2sa_hw.ports.kinds.PORT_KINDS`); ReplayError for a kind without one.

    *rigs* holds what the devices of one service share (the PWM outputs of a servo service). What a
    device needs of its driver's config (a serial device's burst gap) the driver declares
    (``replay_options``, :mod:`u2sa_hw.ports.declared`).
    """
    from u2sa_hw.ports.kinds import PORT_KINDS
    from u2sa_hw.ports.port_kind import load_part

    kind = PORT_KINDS.get(dev.kind)
    if kind is None or not kind.replay:
        raise ReplayError(f"RAW.{dev.name}: replaying {dev.kind or 'unknown'} devices is not supported here; "
                          "leave the device out with --vehicle (a profile without its service)")
    factory = load_part(kind.replay)
    return factory(dev, run_dir, service=service, fast=fast, rigs=rigs if rigs is not None else {})


def make_i2c_device(dev: DevicePlan, run_dir: Path, *, service: ServicePlan, fast: bool,
                    rigs: dict[str, Any]) -> ReplayI2cDevice:
    """The I2C kind's replay device (``PORT_KINDS["i2c"].replay``): a mock bus whose chips answer with the
    recorded reads, its data reads paced by the player."""
    return ReplayI2cDevice(name=dev.name, socket_path=run_dir / f"i2c-{dev.name}.sock", fast=fast)


def make_can_device(dev: DevicePlan, run_dir: Path, *, service: ServicePlan, fast: bool,
                    rigs: dict[str, Any]) -> ReplayCanDevice:
    """The CAN kind's replay device (``PORT_KINDS["can"].replay``): a private stamped udp_multicast bus."""
    return ReplayCanDevice(name=dev.name, port=private_udp_port())


def make_gpio_device(dev: DevicePlan, run_dir: Path, *, service: ServicePlan, fast: bool,
                     rigs: dict[str, Any]) -> Any:
    """The GPIO kind's replay device (``PORT_KINDS["gpio"].replay``): a mock chip driving the recorded edges
    (:mod:`u2sa_hw.hil.replay_gpio`); it needs nothing of the driver's config."""
    from u2sa_hw.hil import replay_gpio

    return replay_gpio.make_device("gpio", dev.name, run_dir, service=service.name, rigs=rigs)


def make_pwm_device(dev: DevicePlan, run_dir: Path, *, service: ServicePlan, fast: bool,
                    rigs: dict[str, Any]) -> Any:
    """The PWM and PCA9685 kinds' replay device: one output of the service's PWM rig (a sysfs-shaped
    directory, or a PCA9685 on a mock I2C bus, per recorded chip; :mod:`u2sa_hw.hil.replay_pwm`)."""
    from u2sa_hw.hil import replay_gpio

    return replay_gpio.make_device("pwm", dev.name, run_dir, service=service.name, rigs=rigs)
