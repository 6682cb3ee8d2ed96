"""GPIO port: input lines with timestamped edge events and output lines, real or mock.

``open_gpio(device=..., chip="/dev/gpiochip0", ...)`` requests the lines from the kernel
through libgpiod v2 (``gpiod`` is imported only then, never at import time);
``chip="mock:/path/to.sock"`` requests them from ``u2sa_hw.mocks.gpio_chip.MockGpioChip``
over a Unix socket. Both hand out the same ``GpioPort``: ``get``, ``set``,
``read_edges`` and ``close``. Edge events carry the timestamp the kernel (or the mock
chip) took when the edge happened, never a time taken when the event was read, because
an RC pulse width is the difference of two such timestamps.

The mock chip's wire protocol and the event types are in :mod:`u2sa_hw.ports.gpio.wire`; the
mock client is :mod:`~u2sa_hw.ports.gpio.mock_client`, the kernel backend :mod:`~u2sa_hw.ports.gpio.gpiod_backend`.

The device clock. :meth:`GpioPort.now_ns` is the time the driver judges timeouts, debounce
and ageing against, on the clock of the edge stamps. A kernel chip stamps edges with
CLOCK_MONOTONIC, so its ``now_ns`` is CLOCK_MONOTONIC now, and so is a mock chip's unless it
says in its request reply that it keeps its own clock (``"clock": "device"``: a replay chip,
hil/replay_gpio.py). Then ``now_ns`` is the latest edge or tick time the driver has taken,
so recorded edges played at any speed are judged as they happened; and it is never held by a
chip that goes quiet: once nothing came from the chip for ``DEVICE_CLOCK_GRACE_S`` of wall
time, the clock runs on with the wall clock from there (a signal timeout then expires).
:meth:`GpioPort.clock_origin_ns` is where the recorded clock's zero lies on the device clock
(0 on a real chip: the device clock *is* CLOCK_MONOTONIC; a replay chip's offset), so a driver's
timed messages fall on the same grid of the recorded clock live and replayed.
:meth:`GpioPort.look_ns` is ``now_ns`` for a driver's look at its clock (what it judges its
timeouts and timed messages at): a look more than ``CLOCK_READ_AFTER_NS`` after the latest edge
read (a lost signal; edges held up on a loaded machine) is tapped as a ``RawGpioClockRead``, so a
replay judges at the very times the live driver did (hil/replay_gpio.py).

Recorded bus inputs. A replay chip can also hand its driver the recorded bus messages the
driver asks for (:meth:`GpioPort.take_recorded_bus`: the RC mux's Health, FAILSAFE and
STATE_ESTIMATE), as :class:`BusInput` events in order with the edges, each stamped on the
device clock where the recording says it arrived. A real chip, and a mock chip without a clock
of its own, never do: their drivers hear the bus.
"""

from __future__ import annotations

import time
from typing import Mapping, Sequence

from u2sa_hw import messages as m
from u2sa_hw.ports.errors import PortClosed
from u2sa_hw.ports.gpio.wire import BIASES, EDGES, EdgeEvent, GpioEvent
from u2sa_hw.ports.tap import Tap, call_tap, tapping

MOCK_PREFIX = "mock:"
# A look at the clock this long after the latest edge read is tapped: closer to an edge, the edges and
# the replay's silence ticks already carry the time (hil/replay_gpio.py STEP_SILENCE_NS is this)
CLOCK_READ_AFTER_NS = 30_000_000


class GpioPort:
    """Requested GPIO lines of one chip; subclasses talk to gpiod or to the mock chip."""

    def __init__(self, *, device: str, address: str, inputs: Sequence[int], outputs: Mapping[int, int],
                 tap: Tap | None) -> None:
        self.device, self.address = device, address
        self.inputs, self.outputs = tuple(inputs), dict(outputs)  # outputs: line -> last value set
        self._tap, self._closed = tap, False
        # edges are tapped (RawGpioEdge) but from a replay chip (a device clock): they are the log's own
        # input played back, and re-tapping them only doubled the replay's bus traffic (writes still are)
        self._tap_edges = True
        self._last_edge_ns: int | None = None   # the latest edge stamp read (for look_ns's tap)

    is_open = property(lambda self: not self._closed, doc="False after close().")

    def get(self, line: int) -> int:
        """The current level (0/1) of a requested input or output line."""
        self._check(line, self.inputs + tuple(self.outputs), "a requested line")
        return self._get(line)

    def set(self, line: int, value: int) -> None:
        """Drive a requested output line to *value* (0/1) and tap the write."""
        self._check(line, tuple(self.outputs), "an output line")
        if value not in (0, 1):
            raise ValueError(f"{self.device}: GPIO value must be 0 or 1, not {value!r}")
        self._set(line, int(value))
        self.outputs[line] = int(value)
        self._tap_write(line, int(value))

    def read_edges(self, timeout: float) -> list[EdgeEvent]:
        """Edges that happened since the last call; waits up to *timeout* s for the first one."""
        return [e for e in self.read_events(timeout) if isinstance(e, EdgeEvent)]

    def now_ns(self) -> int | None:
        """The device clock (see the module docstring): CLOCK_MONOTONIC unless the chip keeps its own;
        None while a chip with its own clock has sent nothing yet."""
        return time.monotonic_ns()

    def look_ns(self) -> int | None:
        """:meth:`now_ns`, for the driver's look at its clock (it judges its timeouts at it): tapped as a
        ``RawGpioClockRead`` when no edge has been read for ``CLOCK_READ_AFTER_NS`` (never from a replay chip,
        whose clock is the log's own)."""
        now = self.now_ns()
        if now is not None and self._tap_edges and tapping(self._tap) and (
                self._last_edge_ns is None or now - self._last_edge_ns > CLOCK_READ_AFTER_NS):
            record = m.RawGpioClockRead()
            record.device, record.clock_ns = self.device, now
            call_tap(self._tap, record)
        return now

    def clock_origin_ns(self) -> int:
        """Where the recorded clock's zero lies on the device clock: 0 but on a replay chip."""
        return 0

    def take_recorded_bus(self, channels: Sequence[str]) -> tuple[str, ...]:
        """Ask the chip for the recorded messages of *channels* as :class:`BusInput` events; the channels it
        will send (none but on a replay chip: the driver then hears the bus)."""
        return ()

    def read_events(self, timeout: float) -> list[GpioEvent]:
        """Edges (and a device-clock chip's ticks and recorded bus inputs) in the order the chip sent them;
        waits up to *timeout* s."""
        self._check_open()
        events = self._read_edges(timeout)
        for event in events:
            if isinstance(event, EdgeEvent) and (self._last_edge_ns is None or event.timestamp_ns > self._last_edge_ns):
                self._last_edge_ns = event.timestamp_ns
        if self._tap_edges and tapping(self._tap):
            for event in events:
                if not isinstance(event, EdgeEvent):
                    continue
                record = m.RawGpioEdge()
                record.device, record.line = self.device, event.line
                record.edge, record.kernel_timestamp_ns = int(event.rising), event.timestamp_ns
                call_tap(self._tap, record)
        return events

    def close(self) -> None:
        """Release the lines; further calls raise PortClosed."""
        if not self._closed:
            self._closed = True
            self._release()

    def _tap_write(self, line: int, value: int) -> None:
        if tapping(self._tap):
            record = m.RawGpioWrite()
            record.device, record.line, record.value = self.device, line, value
            call_tap(self._tap, record)

    def _check_open(self) -> None:
        if self._closed:
            raise PortClosed(self.device, "GPIO port is closed", address=self.address, fix="open the port again")

    def _check(self, line: int, allowed: Sequence[int], what: str) -> None:
        self._check_open()
        if line not in allowed:
            raise ValueError(f"{self.device}: line {line} is not {what} of this port "
                             f"(inputs {list(self.inputs)}, outputs {sorted(self.outputs)})")

    # backend hooks
    def _get(self, line: int) -> int: raise NotImplementedError  # noqa: E704
    def _set(self, line: int, value: int) -> None: raise NotImplementedError  # noqa: E704
    def _read_edges(self, timeout: float) -> list[GpioEvent]: raise NotImplementedError  # noqa: E704
    def _release(self) -> None: raise NotImplementedError  # noqa: E704


def checked_request(*, device: str, inputs: Sequence[int], outputs: Mapping[int, int] | None, edge: str,
                    bias: str) -> tuple[list[int], dict[int, int]]:
    """*inputs* and *outputs* as a list and a dict, once they make a request a chip can grant: ValueError
    (naming *device*) for an unknown *edge* or *bias*, no line, a line twice or an output value not 0/1."""
    inputs, outputs = list(inputs), dict(outputs or {})
    if edge not in EDGES or bias not in BIASES:
        raise ValueError(f"{device}: edge must be one of {EDGES} and bias one of {BIASES}, not {edge!r}, {bias!r}")
    lines = inputs + list(outputs)
    if not lines:
        raise ValueError(f"{device}: a GPIO port needs at least one input or output line")
    if any(not isinstance(n, int) or isinstance(n, bool) or n < 0 for n in lines) or len(set(lines)) != len(lines):
        raise ValueError(f"{device}: line offsets must be distinct non-negative integers, got inputs {inputs} "
                         f"and outputs {sorted(outputs)}")
    if any(v not in (0, 1) for v in outputs.values()):
        raise ValueError(f"{device}: initial output values must be 0 or 1, got {outputs}")
    return inputs, outputs


def open_gpio(*, device: str, chip: str, inputs: Sequence[int] = (), outputs: Mapping[int, int] | None = None,
              edge: str = "both", bias: str = "as-is", tap: Tap | None = None) -> GpioPort:
    """Request *inputs* (with *edge* detection) and *outputs* (line -> initial value) on *chip*.

    *chip* is a kernel GPIO chip (``/dev/gpiochip0``) or ``mock:/path/to.sock``.
    *bias* is one of ``as-is``, ``pull-up``, ``pull-down``, ``disabled`` for every line.
    Raises PortUnavailable (naming the chip and the fix) when the lines cannot be had.
    """
    inputs, outputs = checked_request(device=device, inputs=inputs, outputs=outputs, edge=edge, bias=bias)
    if chip.startswith(MOCK_PREFIX):
        from u2sa_hw.ports.gpio.mock_client import MockGpioPort

        return MockGpioPort(device=device, socket_path=chip[len(MOCK_PREFIX):], inputs=inputs, outputs=outputs,
                            edge=edge, bias=bias, tap=tap)
    from u2sa_hw.ports.gpio.gpiod_backend import GpiodGpioPort

    return GpiodGpioPort(device=device, chip_path=chip, inputs=inputs, outputs=outputs, edge=edge, bias=bias, tap=tap)
