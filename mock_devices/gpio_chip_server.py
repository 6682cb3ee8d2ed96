"""Serving the mock GPIO chip on a Unix socket: :class:`GpioChipServer`, a mixin of ``MockGpioChip``.

It listens at the chip's socket path (replacing a stale socket), gives each connection a
:class:`ChipClient` and two threads: a reader that takes the client's JSON requests off the wire
(``u2sa_hw.ports.gpio.wire`` framing) and hands each to the chip's ``_answer``, and a writer that sends
the client's outbox (replies, edges, ticks, bus messages) in order, every queued frame in one send.
A dropped client (it closed, broke the protocol, or a fault dropped it) releases its lines through
the chip's ``_release_lines``; the output callbacks that fired run after the lock is let go (``_fire``).
The chip (mock_devices/gpio_chip.py) holds the state this uses (``socket_path``, ``label``,
``protocol_errors``, ``_lock``, ``_clients``, ``_stop``, ``_server``, ``_acceptor``) and ``disconnect``.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import socket
import stat
import threading
from dataclasses import dataclass, field
from typing import Any, TypeVar

from u2sa_hw.ports.gpio.wire import MOCK_JSON, MockFrameReader, MockProtocolError

log = logging.getLogger("u2sa_hw.mocks.gpio_chip")

WRITE_BATCH = 256   # frames a client's writer sends at once at most
_Server = TypeVar("_Server", bound="GpioChipServer")


@dataclass
class ChipClient:
    """One connection to the chip: its socket and outbox, and the line request it holds (a kernel request fd)."""

    sock: socket.socket
    consumer: str = ""
    lines: dict[int, dict[str, Any]] = field(default_factory=dict)  # offset -> settings
    outbox: queue.Queue = field(default_factory=lambda: queue.Queue(maxsize=4096))
    global_seqno: int = 0
    line_seqno: dict[int, int] = field(default_factory=dict)
    bus_channels: frozenset = frozenset()     # recorded bus channels it asked for (a device-clock chip's client)
    closed: bool = False


class GpioChipServer:
    """The socket side of the mock chip (see the module docstring)."""

    socket_path: str
    label: str
    protocol_errors: int
    _lock: threading.RLock
    _clients: list[ChipClient]
    _stop: threading.Event
    _server: socket.socket | None
    _acceptor: threading.Thread | None

    def start(self: _Server) -> _Server:
        """Listen on the socket (replacing a stale one) and serve clients on threads."""
        if os.path.exists(self.socket_path) and stat.S_ISSOCK(os.stat(self.socket_path).st_mode):
            os.unlink(self.socket_path)
        server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        server.bind(self.socket_path)
        server.listen(16)
        server.settimeout(0.25)
        self._server = server
        self._stop.clear()
        self._acceptor = threading.Thread(target=self._accept_loop, name=f"{self.label}-accept", daemon=True)
        self._acceptor.start()
        return self

    def stop(self) -> None:
        """Disconnect every client, stop listening and remove the socket file."""
        self._stop.set()
        if self._acceptor is not None:
            self._acceptor.join(timeout=2.0)
        self.disconnect()
        if self._server is not None:
            self._server.close()
            self._server = None
        if os.path.exists(self.socket_path):
            os.unlink(self.socket_path)

    def __enter__(self: _Server) -> _Server:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ---- connections -------------------------------------------------------------------
    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                sock, _ = self._server.accept()  # type: ignore[union-attr]
            except TimeoutError:
                continue
            except OSError:
                return
            sock.settimeout(None)
            client = ChipClient(sock=sock)
            with self._lock:
                self._clients.append(client)
            threading.Thread(target=self._client_reader, args=(client,), daemon=True,
                             name=f"{self.label}-client").start()
            threading.Thread(target=self._client_writer, args=(client,), daemon=True,
                             name=f"{self.label}-writer").start()

    def _client_writer(self, client: ChipClient) -> None:
        # every frame already queued goes out in one send (a replay chip queues edges by the thousand:
        # one syscall, and one wake-up of the client's reader, per frame was most of the cost); order kept
        while True:
            frames = [client.outbox.get()]
            while frames[-1] is not None and len(frames) < WRITE_BATCH:
                try:
                    frames.append(client.outbox.get_nowait())
                except queue.Empty:
                    break
            stop = frames[-1] is None
            if stop:
                frames.pop()
            if frames:
                try:
                    client.sock.sendall(frames[0] if len(frames) == 1 else b"".join(frames))
                except OSError:
                    return
            if stop:
                return

    def _client_reader(self, client: ChipClient) -> None:
        frames = MockFrameReader()
        try:
            while True:
                data = client.sock.recv(65536)
                if not data:
                    break
                for kind, payload in frames.feed(data):
                    if kind != MOCK_JSON:
                        raise MockProtocolError(f"client sent frame kind {kind!r}")
                    self._answer(client, json.loads(payload))
        except OSError:
            pass
        except (MockProtocolError, ValueError, TypeError, AttributeError) as exc:
            self.protocol_errors += 1
            log.warning("%s: dropping client '%s' after a protocol error: %s", self.label, client.consumer, exc)
        self._drop(client)

    def _drop(self, client: ChipClient) -> None:
        fired: list[tuple[int, int, int]] = []
        with self._lock:
            if client.closed:
                return
            client.closed = True
            self._release_lines(client, fired)
            self._clients.remove(client)
        try:
            client.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        client.sock.close()
        while True:  # make room for the writer's stop sentinel
            try:
                client.outbox.put_nowait(None)
                break
            except queue.Full:
                try:
                    client.outbox.get_nowait()
                except queue.Empty:
                    pass
        self._fire(fired)

