"""Presence vectors (thesis 3.2.3.2, 8.2.3.2): bit n is set when the n-th optional field is populated.

:func:`install` adds to a generated LCM class ``set(**fields)`` and ``set_<field>(v)``
setters that keep the presence vector right, and ``has(name)``, ``get(name, default)``,
``clear(name)`` and ``present_fields()`` readers, so no reader takes an absent field for 0.
"""

from __future__ import annotations

from typing import Any, Iterable

from u2sa_hw import lcmtypes

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


class AbsentField(AttributeError):
    """A presence-vector field was read that the message does not carry."""


def _bits(fields: Iterable[str]) -> dict[str, int]:
    return {name: 1 << i for i, name in enumerate(fields)}


def install(cls: type, fields: tuple[str, ...]) -> None:
    """Give *cls* presence-aware setters and readers for *fields* (bit n = fields[n])."""
    bits = _bits(fields)
    cls.PRESENCE_FIELDS = fields

    def _bit(name: str) -> int:
        try:
            return bits[name]
        except KeyError:
            raise AttributeError(f"{cls.__name__} has no optional field {name!r}") from None

    def set_(self: Any, **values: float) -> Any:
        """Set fields by name and mark them present; returns the message."""
        for name, value in values.items():
            bit = _bit(name)
            setattr(self, name, float(value))
            self.presence_vector |= bit
        return self

    def has(self: Any, name: str) -> bool:
        """True when *name* is populated."""
        return bool(self.presence_vector & _bit(name))

    def get(self: Any, name: str, default: Any = None) -> Any:
        """The value of *name*, or *default* when it is absent."""
        return getattr(self, name) if self.presence_vector & _bit(name) else default

    def require(self: Any, name: str) -> float:
        """The value of *name*; :class:`AbsentField` when it is absent."""
        if not self.presence_vector & _bit(name):
            raise AbsentField(f"{cls.__name__}.{name} is not present")
        return getattr(self, name)

    def clear(self: Any, name: str) -> Any:
        """Mark *name* absent (and zero it); returns the message."""
        self.presence_vector &= ~_bit(name)
        setattr(self, name, 0.0)
        return self

    def present_fields(self: Any) -> list[str]:
        """Names of the populated fields, in presence-vector order."""
        pv = self.presence_vector
        return [n for n in fields if pv & bits[n]]

    cls.set = set_
    cls.has = has
    cls.get = get
    cls.require = require
    cls.clear = clear
    cls.present_fields = present_fields
    for name in fields:
        def setter(self: Any, value: float, _name: str = name) -> Any:
            return set_(self, **{_name: value})
        setter.__name__ = f"set_{name}"
        setter.__doc__ = f"Set {name} and mark it present."
        setattr(cls, f"set_{name}", setter)


install(lcmtypes.StateInformation, STATE_FIELDS)
install(lcmtypes.Waypoint, WAYPOINT_FIELDS)
