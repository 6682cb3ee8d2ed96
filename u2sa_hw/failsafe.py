"""One failsafe model for every holder (actuators, the RC mux, control, the HSM).

A failsafe is held *per source*: the ``header.source`` of the :class:`Failsafe` message that
raised it (the HSM, an e-stop input, the operator, ...). The rules, written once here:

1. ``active = true`` from source S holds a failsafe for S (a newer reason replaces the older).
2. ``active = false`` from source S clears S's own failsafe and nobody else's, so an e-stop
   released cannot lower the HSM's failsafe.
3. The operator overrides: a clear from source ``operator`` whose ``service`` field names a
   source clears that source's failsafe, and ``service = "*"`` clears every source
   (``u2sa failsafe clear --source hsm`` / ``--all``). A source whose condition still holds
   raises it again at its next repeat, so an operator clear never hides a live fault for long.
4. Nothing else clears a failsafe: not a timeout, not a restart of the holder. A source that
   dies while holding one leaves it held (fail safe); a restarted holder starts with none and
   learns the others from their repeats (the HSM and e-stop inputs re-send an active failsafe
   every second, and the HSM re-sends the operator's one-shot ``u2sa failsafe raise``).

The system is in failsafe while any source holds one.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

OPERATOR_SOURCE = "operator"
ALL_SOURCES = "*"


@dataclass(frozen=True)
class FailsafeChange:
    """What one message did: whether the overall state changed and the sources that changed."""

    active_before: bool
    active_after: bool
    raised: tuple[str, ...] = ()
    cleared: tuple[str, ...] = ()

    @property
    def edge(self) -> bool:
        """True when the overall failsafe state flipped."""
        return self.active_before != self.active_after


class FailsafeSources:
    """The failsafes held, by source; thread-safe. Feed it every message from ``FAILSAFE``."""

    def __init__(self) -> None:
        self._held: dict[str, str] = {}
        self._lock = threading.Lock()

    @property
    def active(self) -> bool:
        """True while any source holds a failsafe."""
        return bool(self._held)   # one atomic read (the RC mux asks per edge): a snapshot, as under the lock

    def held(self) -> dict[str, str]:
        """A copy of source -> reason for every source holding a failsafe."""
        with self._lock:
            return dict(self._held)

    def reason(self) -> str:
        """One line naming every holder and its reason ("" when none)."""
        if not self._held:   # one atomic read, as in active
            return ""
        with self._lock:
            return "; ".join(f"{src}: {why or 'no reason given'}" for src, why in sorted(self._held.items()))

    def apply(self, *, source: str, active: bool, reason: str = "", target: str = "") -> FailsafeChange:
        """Apply one failsafe message (rules in the module docstring); *target* is its ``service`` field."""
        source = source or "?"
        with self._lock:
            before = bool(self._held)
            raised: tuple[str, ...] = ()
            cleared: list[str] = []
            if active:
                if source not in self._held:
                    raised = (source,)
                self._held[source] = reason
            else:
                victims = [source]
                if source == OPERATOR_SOURCE and target:
                    victims = list(self._held) if target == ALL_SOURCES else [target]
                for victim in victims:
                    if self._held.pop(victim, None) is not None:
                        cleared.append(victim)
            return FailsafeChange(before, bool(self._held), raised, tuple(cleared))

    def apply_message(self, msg: Any) -> FailsafeChange:
        """Apply a :class:`u2sa_hw.lcmtypes.Failsafe` message."""
        return self.apply(source=msg.header.source, active=bool(msg.active), reason=msg.reason,
                          target=msg.service)

    def clear_all(self) -> None:
        """Forget every failsafe (only for a holder that is being reset, e.g. in a test)."""
        with self._lock:
            self._held.clear()
