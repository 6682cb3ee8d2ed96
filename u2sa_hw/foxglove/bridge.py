"""The live Foxglove view of the bus: a WebSocket server (the ``foxglove-sdk`` package) fed from LCM.

The LCM handler thread only appends ``(channel, verified bytes, time)`` to a bounded queue
and returns; when the queue is full the message is dropped and counted (``dropped`` in the
bridge's health), so a slow browser or a busy CPU never slows the bus or the services on it.
A worker thread decodes, maps (``u2sa_hw.foxglove.mapping``, the same mapping as the export)
and logs into the SDK's channels; the JSON text is built only for topics a client subscribed
to. Service log lines are tailed from the profile's ``log_dir`` onto ``/log``.

The SDK server listens on 127.0.0.1 only. Exposing it on a network goes through
:class:`u2sa_hw.foxglove.gate.TokenGate` (the SDK has no authentication hook).
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from u2sa_hw.channels import base_type
from u2sa_hw.foxglove.logs import LogTail
from u2sa_hw.foxglove.mapping import LOG, FoxgloveMapper, Topic
from u2sa_hw.messages import REGISTRY, MalformedMessage
from u2sa_hw.bus.transport import Transport
from u2sa_hw.profile.vehicle import Origin

log = logging.getLogger("u2sa_hw.foxglove")
LOG_POLL_S = 0.5


@dataclass
class BridgeStats:
    """Counters for the bridge's health."""

    received: int = 0        # packets the LCM thread handed over
    dropped: int = 0         # ... that found the queue full
    undecodable: int = 0
    published: int = 0       # messages logged to a topic some client subscribed to
    log_lines: int = 0
    max_delay_ms: float = 0.0   # longest time a message waited in the queue since the last health


class FoxgloveBridge:
    """Subscribes to every channel of *transport* and serves it to Foxglove clients."""

    def __init__(self, transport: Transport, *, origin: Origin | None, port: int = 8765, queue_size: int = 5000,
                 log_dir: Path | None = None, listener: Any = None, name: str = "u2sa") -> None:
        import foxglove

        self._fox = foxglove
        self.transport = transport
        self.mapper = FoxgloveMapper(origin=origin)
        self.stats = BridgeStats()
        self._queue: queue.Queue[tuple[str, bytes, int, float]] = queue.Queue(maxsize=max(1, queue_size))
        self._tail = LogTail(log_dir) if log_dir is not None else None
        self._context = foxglove.Context()
        self._channels: dict[str, Any] = {}
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None
        self._sub: Any = None
        caps = [foxglove.Capability.Parameters] if listener is not None else []
        self.server = foxglove.start_server(name=name, host="127.0.0.1", port=port, capabilities=caps,
                                            server_listener=listener, supported_encodings=["json"],
                                            context=self._context)

    @property
    def port(self) -> int:
        """The port the SDK server listens on (127.0.0.1)."""
        return self.server.port

    def start(self) -> None:
        """Subscribe to the bus and start the worker."""
        self._worker = threading.Thread(target=self._work, name="foxglove-bridge", daemon=True)
        self._worker.start()
        self._sub = self.transport.subscribe(".*", None, self._on_packet, raw=True)

    def _on_packet(self, channel: str, data: bytes) -> None:
        """On the LCM thread: hand over and return at once."""
        self.stats.received += 1
        try:
            self._queue.put_nowait((channel, data, time.time_ns(), time.monotonic()))
        except queue.Full:
            self.stats.dropped += 1

    def _work(self) -> None:
        next_poll = 0.0
        while not self._stop.is_set():
            try:
                channel, data, t_ns, queued = self._queue.get(timeout=LOG_POLL_S)
            except queue.Empty:
                channel = ""
            if channel:
                delay = (time.monotonic() - queued) * 1000.0
                self.stats.max_delay_ms = max(self.stats.max_delay_ms, delay)
                self._handle(channel, data, t_ns)
            if self._tail is not None and time.monotonic() >= next_poll:
                next_poll = time.monotonic() + LOG_POLL_S
                for line_ns, entry in self._tail.poll():
                    self._log(LOG, entry, line_ns)
                    self.stats.log_lines += 1

    def _handle(self, channel: str, data: bytes, t_ns: int) -> None:
        try:
            msg, _ = REGISTRY.decode(data, base_type(channel))
        except MalformedMessage:
            self.stats.undecodable += 1
            return
        try:
            outputs = self.mapper.map(channel, msg, t_ns, wanted=lambda topic: self._channel(topic).has_sinks())
        except Exception:  # noqa: BLE001 - one odd message must not end the live view
            self.stats.undecodable += 1
            log.exception("mapping a %s on %s failed", type(msg).__name__, channel)
            return
        for topic, payload in outputs:
            self._log(topic, payload, t_ns)

    def _channel(self, topic: Topic) -> Any:
        """The SDK channel of *topic*, advertised to clients when first seen."""
        chan = self._channels.get(topic.name)
        if chan is None:
            schema = self._fox.Schema(name=topic.schema_name, encoding="jsonschema", data=topic.schema)
            chan = self._channels[topic.name] = self._fox.Channel(topic.name, schema=schema, message_encoding="json",
                                                                  context=self._context)
        return chan

    def _log(self, topic: Topic, payload: dict[str, Any], t_ns: int) -> None:
        chan = self._channel(topic)
        if chan.has_sinks():
            chan.log(json.dumps(payload, allow_nan=False).encode(), log_time=t_ns)
            self.stats.published += 1

    def describe(self) -> dict[str, Any]:
        """Figures for the service's health (max_delay_ms restarts from 0 each call)."""
        s = self.stats
        out = {"port": self.port, "received": s.received, "dropped": s.dropped, "queue": self._queue.qsize(),
               "undecodable": s.undecodable, "published": s.published, "log_lines": s.log_lines,
               "topics": len(self._channels), "max_delay_ms": round(s.max_delay_ms, 1)}
        s.max_delay_ms = 0.0
        return out

    def stop(self) -> None:
        """Stop the worker and the server (the transport is its owner's)."""
        self._stop.set()
        if self._sub is not None:
            try:
                self.transport.unsubscribe(self._sub)
            except Exception:  # noqa: BLE001 - tearing down
                pass
        if self._worker is not None:
            self._worker.join(timeout=2.0)
        self.server.stop()
