"""What the GPIO drivers share: line-map config parsing and one reconnecting GPIO port.

Config strings (one TOML string each, so they can be changed over the bus like any field):

- a line map ``"throttle=5,steering=6,mode=13"``: name -> line offset on the chip;
- a name list ``"estop,bump_front"``;
- a level map ``"brake=1,horn=0"``;
- a position map ``"bump_front=0.45:0:0.1"``: name -> x:y:z metres in the body frame (FRD).

:class:`GpioLineSet` owns the service's :class:`~u2sa_hw.ports.ReconnectingPort` over
``open_gpio``: a lost chip is reported in health and re-requested with backoff while the
service keeps running. Writes and reads from several threads (the run loop, a FAILSAFE
callback, ``kill``) are serialised by one lock. With ``record_raw`` every edge and write is
published as ``RawGpioEdge`` / ``RawGpioWrite`` on ``RAW.<device>``.
"""

from __future__ import annotations

import threading
from typing import Any, Callable, Mapping, Sequence

from u2sa_hw import lcmtypes as t
from u2sa_hw.config import ConfigError
from u2sa_hw.ports import PortClosed, PortIOError, PortTimeout, PortUnavailable, ReconnectingPort
from u2sa_hw.ports.gpio_port import EdgeEvent, GpioPort, open_gpio
from u2sa_hw.ports.tap import raw_channel
from u2sa_hw.service import U2SAService

_PORT_FAULTS = (PortClosed, PortIOError, PortTimeout)


def _pairs(text: str, *, service: str, key: str, example: str) -> list[tuple[str, str]]:
    pairs = []
    for item in (part.strip() for part in text.split(",")):
        if not item:
            continue
        name, sep, value = item.partition("=")
        if not sep or not name.strip() or not value.strip():
            raise ConfigError(f"service '{service}': config '{key}' item {item!r} is not name=value; "
                              f"write it like \"{example}\"")
        pairs.append((name.strip(), value.strip()))
    names = [n for n, _ in pairs]
    if len(set(names)) != len(names):
        raise ConfigError(f"service '{service}': config '{key}' names a line twice: {text!r}")
    return pairs


def parse_line_map(text: str, *, service: str, key: str) -> dict[str, int]:
    """``"a=5,b=6"`` -> ``{"a": 5, "b": 6}``; ConfigError names the service, the field and the fix."""
    example = "throttle=5,mode=13"
    result: dict[str, int] = {}
    for name, value in _pairs(text, service=service, key=key, example=example):
        if not value.isdigit():
            raise ConfigError(f"service '{service}': config '{key}': line of {name!r} must be a non-negative "
                              f"integer offset (gpioinfo lists them), got {value!r}")
        result[name] = int(value)
    if len(set(result.values())) != len(result):
        raise ConfigError(f"service '{service}': config '{key}' uses one line for two names: {text!r}")
    return result


def parse_names(text: str, *, known: Sequence[str], service: str, key: str) -> list[str]:
    """``"a,b"`` -> ``["a", "b"]``, each one of *known*."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ConfigError(f"service '{service}': config '{key}' names {unknown} which are not configured lines "
                          f"(known: {', '.join(known) or 'none'})")
    return names


def parse_levels(text: str, *, known: Sequence[str], service: str, key: str) -> dict[str, int]:
    """``"brake=1"`` -> ``{"brake": 1}``, each name one of *known* and each level 0 or 1."""
    levels: dict[str, int] = {}
    for name, value in _pairs(text, service=service, key=key, example="brake=1"):
        if name not in known:
            raise ConfigError(f"service '{service}': config '{key}' names {name!r}, not a configured line "
                              f"(known: {', '.join(known) or 'none'})")
        if value not in ("0", "1"):
            raise ConfigError(f"service '{service}': config '{key}': level of {name!r} must be 0 or 1, got {value!r}")
        levels[name] = int(value)
    return levels


def parse_positions(text: str, *, known: Sequence[str], service: str,
                    key: str) -> dict[str, tuple[float, float, float]]:
    """``"bump=0.45:0:0.1"`` -> ``{"bump": (0.45, 0.0, 0.1)}`` (metres, body frame FRD)."""
    positions: dict[str, tuple[float, float, float]] = {}
    for name, value in _pairs(text, service=service, key=key, example="bump_front=0.45:0:0.1"):
        if name not in known:
            raise ConfigError(f"service '{service}': config '{key}' names {name!r}, not a configured line "
                              f"(known: {', '.join(known) or 'none'})")
        try:
            x, y, z = (float(v) for v in value.split(":"))
        except ValueError:
            raise ConfigError(f"service '{service}': config '{key}': position of {name!r} must be x:y:z metres "
                              f"forward:right:down, got {value!r}") from None
        positions[name] = (x, y, z)
    return positions


def check_chip(chip: str, *, service: str) -> None:
    """ConfigError unless a chip address is configured."""
    if not chip.strip():
        raise ConfigError(f"service '{service}': no GPIO chip configured; set chip = \"/dev/gpiochip0\" "
                          "(gpiodetect lists the chips) or a mock chip address \"mock:/path/to.sock\"")


def note_restart_needed(service: U2SAService, name: str, *, live: Sequence[str] = ()) -> None:
    """Log that a changed field of the driver's own CONFIG applies at the next start (lines, chip,
    thresholds are not switched under a running vehicle); fields in *live* are read as they go."""
    own = {f.name for f in type(service).CONFIG}
    if name in own and name not in live:
        service.logger.warning("config '%s' of %s saved; it applies when the service restarts", name, service.name)


class GpioLineSet:
    """The lines one service requests from one chip, behind a reconnecting port.

    *initial_outputs* is called at every (re)open for the output levels to request with,
    so a reopened port starts from what the driver wants (e.g. the safe levels).
    *on_open* is called with the new port right after it opened (in the opening thread).
    """

    def __init__(self, service: U2SAService, *, chip: str, device: str, inputs: Sequence[int] = (),
                 initial_outputs: Callable[[], Mapping[int, int]] = dict, edge: str = "both", bias: str = "as-is",
                 record_raw: bool = False, on_open: Callable[[GpioPort], None] | None = None) -> None:
        check_chip(chip, service=service.name)
        self.service, self.chip, self.device = service, chip, device
        self.inputs, self.edge, self.bias = tuple(inputs), edge, bias
        self._initial_outputs, self._on_open = initial_outputs, on_open
        self._record_raw = record_raw
        self._lock = threading.RLock()
        self.write_errors = 0
        if record_raw:
            service.register_publisher(raw_channel(device), t.RawGpioEdge)
            service.register_publisher(raw_channel(device), t.RawGpioWrite)
        self.reconnecting: ReconnectingPort[GpioPort] = ReconnectingPort(self._open, device=device)

    def _tap(self, record: Any) -> None:
        self.service.publish(raw_channel(self.device), record)

    def _open(self) -> GpioPort:
        port = open_gpio(device=self.device, chip=self.chip, inputs=self.inputs, outputs=dict(self._initial_outputs()),
                         edge=self.edge, bias=self.bias, tap=self._tap if self._record_raw else None)
        if self._on_open is not None:
            try:
                self._on_open(port)
            except BaseException:
                port.close()
                raise
        return port

    @property
    def is_open(self) -> bool:
        """True while the port is open."""
        return self.reconnecting.state == "open"

    def port(self) -> GpioPort | None:
        """The open port (opening it when due), or None while the chip is unavailable or closed."""
        with self._lock:
            try:
                return self.reconnecting.get()
            except (PortUnavailable, PortClosed):
                return None

    def lost(self, exc: BaseException, port: GpioPort) -> None:
        """Mark *port* lost after *exc* and log it on the service."""
        self.reconnecting.lost(exc, port=port)
        self.service.error(str(exc))

    def set(self, line: int, value: int) -> bool:
        """Drive output *line*; False when the port is down or the write failed (counted, port marked lost)."""
        with self._lock:
            port = self.port()
            if port is None:
                return False
            try:
                port.set(line, value)
            except _PORT_FAULTS as exc:
                self.write_errors += 1
                self.lost(exc, port)
                return False
            return True

    def read_edges(self, port: GpioPort, timeout: float) -> list[EdgeEvent]:
        """Edges from *port* within *timeout* s (not under the lock: writes must not wait for it)."""
        try:
            return port.read_edges(timeout)
        except _PORT_FAULTS as exc:
            self.lost(exc, port)
            return []

    def get(self, port: GpioPort, line: int) -> int | None:
        """The level of *line*, or None after a port fault."""
        with self._lock:
            try:
                return port.get(line)
            except _PORT_FAULTS as exc:
                self.lost(exc, port)
                return None

    def retry_in(self) -> float:
        """Seconds until the next open attempt while down."""
        return self.reconnecting.retry_in()

    def close(self) -> None:
        """Release the lines for good."""
        with self._lock:
            self.reconnecting.close()

    def health(self) -> dict[str, Any]:
        """Port state, address, losses, write errors and the last port error while down."""
        rp = self.reconnecting
        return {"port": rp.state, "chip": self.chip, "port_losses": rp.losses, "write_errors": self.write_errors,
                "port_error": str(rp.last_error) if rp.state != "open" and rp.last_error else ""}
