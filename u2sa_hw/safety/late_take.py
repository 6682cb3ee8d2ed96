"""Messages an actuator took late: its bus handling held up, told from each message's header stamp.

When a loaded board holds an actuator's bus handling up (its process not scheduled, its handler
thread waiting on a lock), the commands and RC_MODEs sent meanwhile wait in its socket and are
then taken one after another, late, in order. What the actuator wrote then depended on the load,
not on the messages, and a replay of the recording, which hands the messages over on time, cannot
reproduce it: ``--compare`` reads this watch's counter from the recorded health and reports what
differs around it as a note (hil/held_up.py). It is an observation; it never changes what the gate
admits (the dead-man and the stale-RC_MODE rule do that, on this service's own clock).

How late: a message's header stamp is its sender's wall clock when it was published, so the
delay is ``now - stamp`` on this service's wall clock, plus whatever offset separates the two
clocks (a replay republishes stamps of another day; another machine's clock may be off). Only
the difference from the quickest delay seen lately means something (the offset cancels): a
message taken more than :data:`LATE_S` later than that is late. "Lately" is the current and the
previous :data:`BASELINE_S` span, so a stepped wall clock settles within two spans.
"""

from __future__ import annotations

import time
from typing import Callable

LATE_S = 0.1          # taken this much later than the quickest lately: held up
BASELINE_S = 10.0     # the quickest delay is the least of this span's and the previous one's


class LateTakeWatch:
    """Counts messages taken more than ``late_s`` later than the quickest lately (see the module docstring)."""

    def __init__(self, *, late_s: float = LATE_S, baseline_s: float = BASELINE_S,
                 wall_us: Callable[[], int] = lambda: time.time_ns() // 1000) -> None:
        self.late_s = late_s
        self.baseline_s = baseline_s
        self._wall_us = wall_us
        self._span_start_us: int | None = None
        self._quickest_now: int | None = None      # the least delay (us) of the current span
        self._quickest_before: int | None = None   # ... and of the one before it
        self.late = 0
        self.latest_s = 0.0   # the largest lateness seen (s beyond the quickest)

    def took(self, stamp_us: int) -> bool:
        """A message stamped *stamp_us* (sender's wall clock, us; 0 = unstamped, ignored) is taken now;
        True when it is late (counted)."""
        if stamp_us <= 0:
            return False
        now = self._wall_us()
        delay = now - int(stamp_us)
        if self._span_start_us is None or now - self._span_start_us >= self.baseline_s * 1e6 \
                or now < self._span_start_us:
            self._span_start_us, self._quickest_before, self._quickest_now = now, self._quickest_now, None
        self._quickest_now = delay if self._quickest_now is None else min(self._quickest_now, delay)
        quickest = min(q for q in (self._quickest_now, self._quickest_before) if q is not None)
        lateness = (delay - quickest) / 1e6
        if lateness <= self.late_s:
            return False
        self.late += 1
        self.latest_s = max(self.latest_s, lateness)
        return True

    def details(self) -> dict[str, int | str]:
        """Health details: ``taken_late`` (count) and ``taken_late_max_s``."""
        return {"taken_late": self.late, "taken_late_max_s": f"{self.latest_s:.2f}"}
