"""What the RC mux's state decides to do, handed to the service that carries it out.

:class:`u2sa_hw.drivers.rc_mux.state.MuxState` returns these in the order it decided them; the
service publishes a :class:`ModeReport` as an ``RcMode`` on ``RC_MODE``, a :class:`ManualReport`
as the mixed sticks on ``MANUAL_CMD``, and logs a :class:`Note`. They are plain values, so a test
reads them as they are.
"""

from __future__ import annotations

from typing import NamedTuple, Union


class ModeReport(NamedTuple):
    """What one ``RcMode`` says, as of ``at_ns`` on the device clock (None: before the clock started)."""

    at_ns: int | None
    mode: int
    mode_name: str
    autonomy_enabled: bool
    select_mismatch: bool
    armed: bool
    hold: bool
    blocked_by: str
    pulse_us: list[int]


class ManualReport(NamedTuple):
    """The pilot's sticks as of ``at_ns``: each channel's last valid width in us (0: none), for the manual mixer."""

    at_ns: int
    widths_us: dict[str, int]


class Note(NamedTuple):
    """A line for the log: ``level`` is ``info``, ``warning`` or ``error`` (an error is also the service's
    last error, shown in its health)."""

    level: str
    text: str


Output = Union[ModeReport, ManualReport, Note]
