"""Service configs as Foxglove parameters (``<service>.<field>``), through the service contract.

Reading asks every live service for its config over the bus (the services that answer
discovery and those whose health the bridge has heard, then a ``ConfigRequest`` each: on a
busy machine a discovery answer can come after the discovery's wait, a health message was
already there). Writing is off unless the bridge was started with parameter
writes allowed, and it is refused on an open bus: a write becomes a ``ConfigChange``
published by :class:`u2sa_hw.bus.client.BusClient`, signed with the vehicle's key like
``u2sa param set``, and the service checks it exactly as it checks that command's. A
refused or unanswered write is reported to the client as a status message, and the
parameter comes back with the value the service still has.
"""

from __future__ import annotations

import logging
import threading
import tomllib
from typing import Any, Callable, Iterable

from u2sa_hw.config.fields import to_text

log = logging.getLogger("u2sa_hw.foxglove")
DISCOVERY_TIMEOUT_S = 1.0
CONFIG_TIMEOUT_S = 3.0


def _native(text: str) -> Any:
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


class ParameterBridge:
    """A ``foxglove.websocket.ServerListener`` answering parameter requests from the bus."""

    def __init__(self, bus: Any, *, allow_writes: bool, status: Callable[[str, str], None] | None = None,
                 heard: Callable[[], Iterable[str]] = lambda: ()) -> None:
        self.bus = bus
        self.heard = heard   # the services whose health the bridge has heard
        self.allow_writes = allow_writes and bus.transport.auth is not None
        self.refused_open_bus = allow_writes and not self.allow_writes
        self.status = status or (lambda _level, _text: None)   # (level, text) -> the clients' status bar
        self._lock = threading.Lock()
        self.values: dict[str, Any] = {}
        self.writes = self.refused = 0

    def _parameters(self, names: list[str]) -> list[Any]:
        import foxglove

        wanted = names or sorted(self.values)
        out = []
        for name in wanted:
            if name in self.values:
                value = self.values[name]
                hint = foxglove.ParameterType.Float64 if isinstance(value, float) else None
                out.append(foxglove.Parameter(name, value=value, type=hint))
        return out

    def _read_service(self, service: str) -> None:
        resp = self.bus.get_config(service, timeout=CONFIG_TIMEOUT_S)
        if resp is None or not resp.ok:
            return
        for f in resp.fields:
            self.values[f"{service}.{f.name}"] = _native(f.value)

    def refresh(self, names: list[str]) -> None:
        """Read the configs of the services *names* mention (all live ones when empty)."""
        services = sorted({n.split(".", 1)[0] for n in names if "." in n})
        if not services:
            services = sorted({r.name for r in self.bus.discover(timeout=DISCOVERY_TIMEOUT_S)} | set(self.heard()))
        for service in services:
            self._read_service(service)

    def on_get_parameters(self, client: Any, param_names: list[str], request_id: str | None = None) -> list[Any]:
        """Answer ``getParameters``: every service's config, or the named parameters."""
        with self._lock:
            try:
                self.refresh(param_names)
            except Exception:  # noqa: BLE001 - the server must still answer
                log.exception("reading service configs for Foxglove failed")
            return self._parameters(param_names)

    def on_set_parameters(self, client: Any, parameters: list[Any], request_id: str | None = None) -> list[Any]:
        """Answer ``setParameters``: each change as a signed ConfigChange, when writes are allowed."""
        with self._lock:
            names = [p.name for p in parameters]
            if not self.allow_writes:
                self.refused += len(parameters)
                why = ("the bus is open (unsigned): nothing would authenticate the change" if self.refused_open_bus
                       else "parameter writes are off (start the bridge with --allow-parameter-writes)")
                self.status("warning", f"parameters not changed: {why}")
                self.refresh(names)
                return self._parameters(names)
            for p in parameters:
                service, _, field_name = p.name.partition(".")
                value = p.get_value()
                if not field_name or value is None:
                    self.status("error", f"{p.name}: not <service>.<field> with a value")
                    continue
                resp = self.bus.set_config(service, field_name, to_text(value), timeout=CONFIG_TIMEOUT_S)
                if resp is None:
                    self.status("error", f"{p.name}: service '{service}' did not answer")
                elif not resp.ok:
                    self.status("error", f"{p.name}: {service} refused: {resp.error}")
                else:
                    self.writes += 1
                    log.info("parameter %s set to %s from Foxglove client %s", p.name, to_text(value),
                             getattr(client, "id", "?"))
            self.refresh(names)
            return self._parameters(names)

    # The rest of the ServerListener protocol: nothing to do.
    def on_subscribe(self, client: Any, channel: Any) -> None:
        """A client subscribed to a topic."""

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        """A client unsubscribed from a topic."""

    def on_parameters_subscribe(self, param_names: list[str]) -> None:
        """A client subscribed to parameter updates."""

    def on_parameters_unsubscribe(self, param_names: list[str]) -> None:
        """The last client unsubscribed from parameter updates."""
