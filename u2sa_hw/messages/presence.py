"""Presence vectors (thesis 3.2.3.2, 8.2.3.2): bit n is set when the n-th optional field is populated.

This module says which fields of which type have a presence bit, in the thesis's order.
``u2sa_hw.message_codegen`` generates from it, into each such class in ``u2sa_hw.lcmtypes``,
``set(**fields)`` and ``set_<field>(v)`` setters that keep the presence vector right, and
``has(name)``, ``get(name, default)``, ``require(name)``, ``clear(name)`` and
``present_fields()`` readers, so no reader takes an absent field for 0. The generated
classes work without importing this package (``u2sa_hw.lcmtypes.StateInformation().set(x=1)``).
"""

from __future__ import annotations

# Figure 6, column by column: position and its derivatives, attitude and its derivatives,
# fluid velocity and acceleration; each block followed by a sigma for each of its values.
_COLUMNS = (
    ("x", "y", "z", "x_dot", "y_dot", "z_dot", "x_ddot", "y_ddot", "z_ddot"),
    ("phi", "theta", "psi", "phi_dot", "theta_dot", "psi_dot", "phi_ddot", "theta_ddot", "psi_ddot"),
    ("fluid_x_dot", "fluid_y_dot", "fluid_z_dot", "fluid_x_ddot", "fluid_y_ddot", "fluid_z_ddot"),
)
STATE_FIELDS: tuple[str, ...] = tuple(
    name for column in _COLUMNS for name in (*column, *(f"{v}_sigma" for v in column))
)
WAYPOINT_FIELDS: tuple[str, ...] = ("x", "y", "z", "phi", "theta", "psi", "time", "vertical_threshold")

# type name -> its optional fields, bit n = fields[n] (the generator reads this)
PRESENCE: dict[str, tuple[str, ...]] = {"StateInformation": STATE_FIELDS, "Waypoint": WAYPOINT_FIELDS}


class AbsentField(AttributeError):
    """A presence-vector field was read that the message does not carry."""
