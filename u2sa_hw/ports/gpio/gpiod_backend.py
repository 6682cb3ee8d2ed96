"""The kernel GPIO backend: lines of a ``/dev/gpiochipN`` character device through libgpiod v2.

``gpiod`` is imported when a port opens, never at import time.
"""

from __future__ import annotations

import errno
import threading
from contextlib import contextmanager
from typing import Any, Iterator, Mapping, Sequence

from u2sa_hw.ports.errors import PortClosed, PortUnavailable
from u2sa_hw.ports.gpio.port import GpioPort
from u2sa_hw.ports.gpio.wire import EdgeEvent
from u2sa_hw.ports.tap import Tap


class GpiodGpioPort(GpioPort):
    """Lines of a kernel GPIO character device, through libgpiod v2."""

    def __init__(self, *, device: str, chip_path: str, inputs: Sequence[int], outputs: Mapping[int, int],
                 edge: str, bias: str, tap: Tap | None) -> None:
        super().__init__(device=device, address=chip_path, inputs=inputs, outputs=outputs, tap=tap)
        try:
            import gpiod
            from gpiod.line import Bias, Direction, Edge, Value
        except ImportError as exc:
            raise PortUnavailable(device, f"cannot use {chip_path}: the gpiod (libgpiod v2) bindings are missing",
                                  address=chip_path, fix="pip install 'gpiod>=2.1' into the u2sa venv") from exc
        self._gpiod = gpiod
        bias_setting, edge_setting = Bias[bias.replace("-", "_").upper()], Edge[edge.upper()]
        config: dict[int, Any] = {n: gpiod.LineSettings(direction=Direction.INPUT, edge_detection=edge_setting,
                                                        bias=bias_setting) for n in inputs}
        for n, value in outputs.items():
            config[n] = gpiod.LineSettings(direction=Direction.OUTPUT, bias=bias_setting,
                                           output_value=Value.ACTIVE if value else Value.INACTIVE)
        self._lock = threading.Lock()
        try:
            self._request = gpiod.request_lines(chip_path, config=config, consumer=f"u2sa:{device}")
        except OSError as exc:
            raise self._open_error(exc, list(config)) from exc
        except ValueError as exc:
            raise PortUnavailable(device, f"cannot request lines {sorted(config)}: {exc}", address=chip_path,
                                  fix="use line offsets the chip has (gpioinfo lists them)") from exc
        for n, value in outputs.items():
            self._tap_write(n, value)

    def _open_error(self, exc: OSError, offsets: list[int]) -> PortUnavailable:
        path, code = self.address, exc.errno
        if code == errno.ENOENT:
            message, fix = f"GPIO chip {path} does not exist", ("list the chips with `gpiodetect` and put the right "
                                                                "/dev/gpiochipN in the service config, or use a mock "
                                                                "chip address mock:/path.sock")
        elif code in (errno.EACCES, errno.EPERM):
            message, fix = f"no permission to open {path}", (f"add the service user to group gpio (usermod -aG gpio "
                                                             f"<user>) and give {path} to group gpio with a udev rule "
                                                             "(u2sa install does both)")
        elif code == errno.EBUSY:
            message, fix = f"GPIO lines in use: {self._line_users(offsets)}", (
                "stop the process holding the line (gpioinfo shows the consumer) or change the line in this "
                "service's config")
        elif code in (errno.ENODEV, errno.ENOTTY):
            message, fix = f"{path} is not a GPIO character device", "point the config at a /dev/gpiochipN (gpiodetect)"
        else:
            message, fix = f"cannot request GPIO lines {offsets}: {exc.strerror}", "check the lines against `gpioinfo`"
        return PortUnavailable(self.device, message, address=path, fix=fix)

    def _line_users(self, offsets: list[int]) -> str:
        try:
            with self._gpiod.Chip(self.address) as chip:
                infos = [chip.get_line_info(n) for n in offsets]
        except (OSError, ValueError):
            return f"one of lines {offsets} (consumer unknown)"
        return ", ".join(f"line {i.offset} by '{i.consumer or 'unnamed'}'" for i in infos if i.used) or str(offsets)

    @contextmanager
    def _request_failures(self) -> Iterator[None]:
        try:
            yield
        except (OSError, self._gpiod.RequestReleasedError) as exc:
            raise PortClosed(self.device, f"GPIO request failed ({exc})", address=self.address,
                             fix="check the chip; the driver re-requests the lines") from exc

    def _get(self, line: int) -> int:
        with self._request_failures(), self._lock:
            return 1 if self._request.get_value(line) else 0

    def _set(self, line: int, value: int) -> None:
        level = self._gpiod.line.Value.ACTIVE if value else self._gpiod.line.Value.INACTIVE
        with self._request_failures(), self._lock:
            self._request.set_value(line, level)

    def _read_edges(self, timeout: float) -> list[EdgeEvent]:
        rising = self._gpiod.EdgeEvent.Type.RISING_EDGE
        with self._request_failures():
            # the wait is a poll() on the request fd; only the read needs the lock
            if not self._request.wait_edge_events(timeout):
                return []
            with self._lock:
                events = self._request.read_edge_events()
        return [EdgeEvent(line=e.line_offset, rising=e.event_type is rising, timestamp_ns=e.timestamp_ns)
                for e in events]

    def _release(self) -> None:
        with self._lock:
            self._request.release()
