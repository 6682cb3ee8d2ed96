"""What the GPIO drivers share: line-map config parsing and one reconnecting GPIO port.

Config strings (one TOML string each, so they can be changed over the bus like any field):

- a line map ``"throttle=5,steering=6,mode=13"``: name -> line offset on the chip;
- a name list ``"estop,bump_front"``;
- a level map ``"brake=1,horn=0"``;
- a position map ``"bump_front=0.45:0:0.1"``: name -> x:y:z metres in the body frame (FRD).

:class:`GpioLineSet` owns the service's :class:`~u2sa_hw.ports.device_link.DeviceLink`
(the ``device`` setting, default the service name; its address ``gpio://CHIP/LINES`` from the
profile's ``[devices.NAME]``): a lost chip is reported in health and re-requested with backoff while the
service keeps running. Writes and reads from several threads (the run loop, a FAILSAFE
callback, ``kill``) are serialised by one lock. With ``record_raw`` every edge and write is
published as ``RawGpioEdge`` / ``RawGpioWrite`` on ``RAW.<device>``.
"""

from __future__ import annotations

import threading
from typing import Any, Callable, Mapping, Sequence

from u2sa_hw import lcmtypes as t
from u2sa_hw.config.fields import ConfigError
from u2sa_hw.ports import PortClosed, PortIOError, PortTimeout, PortUnavailable
from u2sa_hw.ports.address import AddressError, make_address
from u2sa_hw.ports.device_link import DeviceLink, device_setting
from u2sa_hw.ports.gpio.wire import ClockTick, EdgeEvent
from u2sa_hw.ports.gpio.port import GpioPort
from u2sa_hw.service.contract import U2SAService

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


def check_gpio_device(service: U2SAService, config: Mapping[str, Any], lines: Sequence[int]) -> None:
    """ConfigError unless the service's GPIO device has an address (``[devices.NAME]``) that lists every one
    of *lines* (or lists none); the error names the missing lines and the address to write."""
    from u2sa_hw.profile.devices import device_address

    device = device_setting(config, service.name)
    try:
        address = device_address(service.profile, device)
    except AddressError as exc:
        raise ConfigError(f"service '{service.name}': {exc} (e.g. \"gpio://gpiochip0/{','.join(map(str, lines))}\"; "
                          "gpiodetect lists the chips)") from None
    if address.kind != "gpio":
        raise ConfigError(f"service '{service.name}': device '{device}' has the {address.kind} address "
                          f"{address.url}; a GPIO driver needs a gpio:// address")
    missing = sorted(set(lines) - set(address.lines)) if address.lines else []
    if missing:   # the port would refuse them at every open: an e-stop or enable line never requested
        full = make_address("gpio", address.location, sorted({*address.lines, *lines}), mock=address.mock,
                            device=device)
        raise ConfigError(f"service '{service.name}': device '{device}' address {address.url} does not list "
                          f"line(s) {', '.join(map(str, missing))} that the service uses; list every line: "
                          f"[devices.{device}] address = \"{full.url}\"")


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

    def __init__(self, service: U2SAService, *, inputs: Sequence[int] = (),
                 initial_outputs: Callable[[], Mapping[int, int]] = dict, edge: str = "both", bias: str = "as-is",
                 record_raw: bool = False, on_open: Callable[[GpioPort], None] | None = None) -> None:
        config = service.config
        self.service = service
        self.inputs, self.edge, self.bias = tuple(inputs), edge, bias
        self._initial_outputs = initial_outputs
        self._lock = threading.RLock()
        self.write_errors = 0
        lines = [*self.inputs, *initial_outputs()]
        check_gpio_device(service, config, lines)
        self.reconnecting: DeviceLink[GpioPort] = DeviceLink(
            service, device=lambda: device_setting(config, service.name), raw_type=(t.RawGpioEdge, t.RawGpioWrite, t.RawGpioClockRead),
            on_open=on_open, record=lambda: record_raw,
            options=lambda: {"inputs": self.inputs, "outputs": dict(self._initial_outputs()), "edge": self.edge,
                             "bias": self.bias})
        self.reconnecting.start()
        self.device = self.reconnecting.device
        self.chip = self.reconnecting.address.gpio_chip if self.reconnecting.address is not None else ""

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

    def read_events(self, port: GpioPort, timeout: float) -> list[EdgeEvent | ClockTick]:
        """Edges and device-clock ticks from *port*, in order (see read_edges)."""
        try:
            return port.read_events(timeout)
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
        return {**self.reconnecting.health(), "chip": self.chip, "write_errors": self.write_errors}
