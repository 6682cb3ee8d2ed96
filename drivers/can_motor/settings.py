"""The settings every CAN motor driver has, and the check that they fit together.

:class:`CanMotorSettings` is a mixin of :class:`~u2sa_hw.drivers.can_motor.common.CanMotorService`:
the shared ``CONFIG`` (the bus, one name, id, direction and wheel radius per controller, command
timing, odometry), :meth:`~CanMotorSettings.check_settings` (the combinations a field's own bounds
cannot say; the ODrive and VESC drivers add theirs) and ``_fail`` (a ConfigError naming the
service). :class:`MotorSpec` is one controller as configured; ``PORT_FIELDS`` and
``ODOMETRY_FIELDS`` are the fields whose change reopens the bus or restarts the odometry.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, ClassVar

from u2sa_hw.config.fields import MAX_TIMEOUT_S, ConfigError, field

from u2sa_hw.drivers.can_motor.diff_drive_odometry import SOURCES

PORT_FIELDS = frozenset({"device", "device_name"})
ODOMETRY_FIELDS = frozenset({"odometry", "odometry_left", "odometry_right", "track_width_m", "odometry_source",
                             "odometry_window_s", "wheel_radius_m", "directions"})


@dataclass(frozen=True)
class MotorSpec:
    """One controller as configured: actuator name, CAN id, direction (+1/-1), wheel radius (m)."""

    name: str
    can_id: int
    direction: int
    radius_m: float


class CanMotorSettings:
    """The shared fields and their check (see the module docstring); ``name`` is the service's."""

    name: str
    ID_FIELD: ClassVar[str]   # the setting holding the controllers' CAN ids (the driver's)
    CONFIG = (
        field("device", "", "the bus: its [devices.NAME] table (address) and RAW.<device> (empty: the service name)"),
        field("device_name", "", "old name of the device setting"),
        field("record_raw", False, "publish every frame sent and received as RawCanFrame on RAW.<device>"),
        field("actuators", ["left", "right"], "actuator names, one per controller (Percentage Commands address them)", item_type=str),
        field("directions", [1, 1], "+1 or -1 per controller: -1 where forward means turning the motor backwards", item_type=int, ge=-1, le=1),
        field("wheel_radius_m", [0.1, 0.1], "wheel radius per controller (m), for the odometry", item_type=float, gt=0, le=10.0),
        field("command_period_s", 0.05, "setpoints are re-sent this often (keeps the controller's timeout fed)", gt=0, le=MAX_TIMEOUT_S),
        field("silent_after_s", 0.5, "no frame from a controller for this long -> 'silent' and degraded", gt=0, le=MAX_TIMEOUT_S),
        field("odometry", True, "publish body speed (x_dot, FRD) and yaw rate from the differential wheel pair"),
        field("odometry_left", "left", "the actuator name of the left wheel"),
        field("odometry_right", "right", "the actuator name of the right wheel"),
        field("track_width_m", 0.5, "distance between the left and right wheels' contact lines (m)", gt=0, le=100.0),
        field("odometry_source", "velocity", "velocity: the controller's speed estimate; position: travel deltas",
              choices=SOURCES),
        field("odometry_window_s", 0.1, "position source: travel deltas over this window (s)", gt=0, le=MAX_TIMEOUT_S),
        field("speed_sigma_mps", 0.05, "sigma of the published x_dot and y_dot (m/s)", gt=0, le=100.0),
        field("yaw_rate_sigma_rad_s", 0.05, "sigma of the published psi_dot (rad/s)", gt=0, le=10.0),
    )

    def _fail(self, text: str) -> ConfigError:
        return ConfigError(f"service '{self.name}': {text}")

    def check_settings(self, get: Callable[[str], Any]) -> None:
        """Raise ConfigError (naming the field and the fix) unless the values *get* returns can run together:
        one id, direction and radius per actuator. Each field's own type, choices and bounds are declared."""
        names, ids = get("actuators"), get(self.ID_FIELD)
        dirs = get("directions")
        if not names or not all(n.strip() for n in names) or len(set(names)) != len(names):
            raise self._fail(f"actuators must be distinct non-empty names, got {names!r}; name each controller once")
        for key in (self.ID_FIELD, "directions", "wheel_radius_m"):
            if len(get(key)) != len(names):
                raise self._fail(f"{key} needs one entry per actuator ({len(names)}: {', '.join(names)}), "
                                 f"got {get(key)!r}")
        if len(set(ids)) != len(ids):
            raise self._fail(f"{self.ID_FIELD} must be distinct (one controller per CAN id), got {ids!r}; "
                             "give each controller its own id")
        if any(d not in (1, -1) for d in dirs):
            raise self._fail(f"directions must be 1 or -1 per actuator, got {dirs!r}; write -1 where forward "
                             "turns the motor backwards")
        if get("odometry"):
            for key in ("odometry_left", "odometry_right"):
                if get(key) not in names:
                    raise self._fail(f"{key} = {get(key)!r} is not one of the actuators ({', '.join(names)}); "
                                     "name the wheel, or set odometry = false")
