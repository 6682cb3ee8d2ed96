"""The mux's select read-back against the enable line, as pure logic.

With a ``select_line`` the mux's select output is read as an input (1 = autonomous) and compared
with the enable line. A disagreement that lasts longer than ``select_mismatch_ms`` is a mismatch
(an error naming the line and the fix; it disarms), until the two agree again. The time it starts
and expires is the device clock's, given by :class:`u2sa_hw.drivers.rc_mux.state.MuxState`.
"""

from __future__ import annotations

from u2sa_hw.drivers.rc_mux.outputs import Note


class SelectReadback:
    """The read-back's level, a disagreement pending since when, and the mismatch it became."""

    def __init__(self, *, line: int | None, mismatch_ms: float, device: str) -> None:
        self.line = line
        self.mismatch_ms = mismatch_ms
        self.device = device
        self.level: int | None = None      # the select line's level (None: no read-back)
        self.mismatch = False
        self.since: int | None = None      # a disagreement pending since then (device clock, ns)
        self.mismatches = 0

    def expiry_ns(self) -> int | None:
        """When a pending disagreement becomes a mismatch (None: none pending)."""
        if self.since is None or self.mismatch:
            return None
        return self.since + int(self.mismatch_ms * 1e6) + 1

    def check(self, now_ns: int, *, enabled: bool, notes: list[Note]) -> bool:
        """The read-back against the line (*enabled*) at *now_ns*: a disagreement starts, becomes a mismatch
        (True: it just did) or ends."""
        if self.level is None:
            return False
        if self.level == int(enabled):
            if self.mismatch:
                notes.append(Note("info", f"mux select read-back agrees again "
                                          f"({'autonomous' if enabled else 'rc'})"))
                self.mismatch = False
            self.since = None
            return False
        if self.since is None:
            self.since = now_ns
        elif not self.mismatch and now_ns - self.since > self.mismatch_ms * 1e6:
            self.mismatch = True
            self.mismatches += 1
            notes.append(Note("error", f"{self.device}: mux select line {self.line} reads "
                                       f"{'autonomous' if self.level else 'rc'} but autonomy enable is "
                                       f"{'high' if enabled else 'low'}; check the mux wiring and its mode channel"))
            return True
        return False

    def start_if_disagrees(self, at_ns: int, *, enabled: bool) -> None:
        """The line just settled at *at_ns*: a disagreement with it counts from now."""
        if self.level is not None and self.since is None and self.level != int(enabled):
            self.since = at_ns
