"""When a heartbeat was sent, on the HSM's own clock, from the stamp the service put on it.

A Health message's ``header.timestamp_us`` is the sender's CLOCK_REALTIME when it published.
The HSM judges with its monotonic clock, and may read a message late (it was paused, its
handler thread was busy): the time it *received* a heartbeat then says the service was alive
later than it was, and a heartbeat read before a backlog is drained says it was silent longer
than it was. So the HSM measures between stamps, never across clocks:

    sent(n) = min(received(n), sent(n-1) + (stamp(n) - stamp(n-1)) + CATCH_UP * (received(n) - received(n-1)))

- Only differences of one sender's stamps are used, so the sender's clock may be anywhere
  (another board, an SBC without RTC that still thinks it is 1970).
- A backlog read in one go keeps the spacing the service sent it with: the newest heartbeat of
  a backlog counts from when it was sent, not from when it was read.
- ``min(received, ...)``: a heartbeat is never younger than its reception says, so a stamp that
  jumps ahead (the sender's clock stepped forward) changes nothing.
- A stamp that goes back while the sequence goes on (the clock stepped back) re-anchors on
  the reception time; so does a message without a stamp or from a new process.
- ``CATCH_UP`` (5 % of the time between receptions) lets an estimate that fell behind (a small
  backward step, a sender clock running slow) converge back to the reception times.
- A message whose sequence is not newer than the last one's (a duplicate, a reordered
  datagram) tells nothing new: :meth:`SenderClock.sent_at` returns None.
"""

from __future__ import annotations

CATCH_UP = 0.05


class SenderClock:
    """The send times of one sender's messages (one process: reset it when the pid changes)."""

    def __init__(self) -> None:
        self._stamp: float | None = None      # sender's clock, seconds
        self._sequence = 0
        self._sent: float = 0.0               # our clock
        self._received: float = 0.0

    def reset(self) -> None:
        """Forget the anchor (a new process of the service)."""
        self._stamp, self._sequence = None, 0

    def sent_at(self, *, stamp_us: int, sequence: int, received: float) -> float | None:
        """When the message stamped *stamp_us* with *sequence*, received at *received*, was sent; None if stale.

        *received* and the result are on the caller's clock (monotonic seconds). A zero
        *sequence* or *stamp_us* means the sender gave none.
        """
        if sequence and self._sequence and sequence <= self._sequence:
            return None
        stamp = stamp_us / 1e6 if stamp_us > 0 else None
        if stamp is None or self._stamp is None or stamp < self._stamp:
            sent = received
        else:
            sent = min(received, self._sent + (stamp - self._stamp) + CATCH_UP * (received - self._received))
        self._stamp, self._sequence = stamp, sequence or self._sequence
        self._sent, self._received = sent, received
        return sent
