"""What install makes of a real sysfs PWM address: its service's unit gets the ``50-pwm-sysfs.conf`` drop-in.

:func:`u2sa_hw.install.udev.plan_devices` calls :func:`plan_device` for each real PWM address
(a PCA9685 is an I2C chip: ``udev/60-u2sa-permissions.rules`` covers its adapter).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Collection

if TYPE_CHECKING:
    from u2sa_hw.ports.address import DeviceAddress


def plan_device(plan: Any, name: str, address: DeviceAddress, *, service: str | None, elsewhere: Collection[str],
                fail: Callable[[str], Exception]) -> None:
    """Note in *plan* (a ``DevicePlan``) that *service*'s unit drives the sysfs chip of *address*."""
    if service:
        plan.pwm_services.setdefault(service, address.pwm_chip)
