"""The services the launcher starts first and stops last (the recorders), for :class:`~.launcher.Launcher`.

They start alone, and the others once they are ready (or ``first_wait_s`` later: one that never gets ready
holds nobody back for long), so a recording holds every service's start-up I/O (an IMU's identification
reads, a motor controller's arming), which replay needs. On a stop they get their SIGTERM once every other
child has exited (each bounded by the stop's SIGKILL rules), as systemd stops the units ordered after a
recorder before it: the recording holds every service's stop too (its ``stopping`` health, its last
writes). Called from the launcher's loop thread only.
"""

from __future__ import annotations

import time
from typing import Callable, Mapping

from u2sa_hw.launcher.policy import EXITED, FAILED, STOPPED
from u2sa_hw.launcher.process import SupervisedProcess


class FirstServices:
    """The start-first, stop-last services *names* among *total* children; *say* logs the launcher's lines."""

    def __init__(self, names: list[str], *, total: int, wait_s: float, say: Callable[[str], None],
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.names = names
        self.wait_s = wait_s
        self._say = say
        self._clock = clock
        self._others = len(names) < total          # with no other service there is nothing to order
        self.holding = bool(names) and self._others
        self._hold_since: float | None = None
        self._stop_last: list[str] = []           # still to stop once the others have exited

    def holds_back(self, name: str) -> bool:
        """Whether service *name* must wait: the hold is on and it is not one of the first."""
        return self.holding and name not in self.names

    def still_holding(self, processes: Mapping[str, SupervisedProcess]) -> bool:
        """True while the first services are neither ready nor done and ``wait_s`` has not passed; says when
        the hold ends, and why."""
        if not self.holding:
            return False
        now = self._clock()
        if self._hold_since is None:
            self._hold_since = now
        waiting = [n for n in self.names
                   if not processes[n].ready and processes[n].state not in (FAILED, EXITED, STOPPED)]
        if waiting and now - self._hold_since < self.wait_s:
            return True
        self.holding = False
        if waiting:
            self._say(f"{', '.join(waiting)} not ready after {self.wait_s:g} s: starting the others anyway")
        else:
            self._say(f"starting the others now that {', '.join(self.names)} "
                      f"{'is' if len(self.names) == 1 else 'are'} ready")
        return False

    def hold_deadline(self) -> float | None:
        """When the current hold ends at the latest (the launcher's clock), None when not holding."""
        return self._hold_since + self.wait_s if self.holding and self._hold_since is not None else None

    def begin_stop(self) -> str:
        """The stack stops: the first services are kept for last; returns the words for the stop's line."""
        self.holding = False
        self._stop_last = list(self.names) if self._others else []
        return f"; {', '.join(self._stop_last)} once the others have exited" if self._stop_last else ""

    def kept_for_last(self, name: str) -> bool:
        """Whether *name* is a first service still waiting for the others to exit before its stop."""
        return name in self._stop_last

    def due_to_stop(self, processes: Mapping[str, SupervisedProcess]) -> list[str]:
        """The first services to stop now: every other child has exited (once; [] before and after)."""
        if not self._stop_last or any(p.proc is not None for n, p in processes.items() if n not in self._stop_last):
            return []
        due, self._stop_last = self._stop_last, []
        return due
