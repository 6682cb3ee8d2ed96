"""A token check in front of the Foxglove server, for exposing it beyond this machine.

The ``foxglove-sdk`` server has no authentication hook, so it always listens on 127.0.0.1
and, when the bridge is to be reached from a network, this gate listens on the public
address: it reads the client's HTTP upgrade request, lets it through to the server only
when it carries the token (``?token=...`` in the URL, which is what Foxglove's "Open
connection" dialog can send, or an ``Authorization: Bearer ...`` header) and answers
``401`` otherwise, then copies bytes both ways. With a certificate it speaks TLS, so the
token does not cross the network in clear text.
"""

from __future__ import annotations

import asyncio
import hmac
import logging
import ssl
import threading
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

log = logging.getLogger("u2sa_hw.foxglove")
HEAD_LIMIT = 16 * 1024
HEAD_TIMEOUT_S = 5.0
MIN_TOKEN_LEN = 16


class GateError(ValueError):
    """The gate cannot be set up; the message says why and how to fix it."""


def read_token(path: Path) -> str:
    """The token in *path* (first line); GateError when missing or too short to resist guessing."""
    try:
        text = path.read_text().strip()
    except OSError as exc:
        raise GateError(f"{path}: cannot read the Foxglove token file ({exc.strerror}); create one with "
                        f"'head -c 24 /dev/urandom | base64 > {path}; chmod 600 {path}'") from None
    token = text.splitlines()[0].strip() if text else ""
    if len(token) < MIN_TOKEN_LEN:
        raise GateError(f"{path}: the token must be at least {MIN_TOKEN_LEN} characters "
                        f"('head -c 24 /dev/urandom | base64 > {path}')")
    return token


def token_of(head: bytes) -> str:
    """The token an HTTP request head carries (query ``token`` or a bearer Authorization), or ''."""
    lines = head.decode("latin-1").split("\r\n")
    parts = lines[0].split(" ")
    if len(parts) >= 2:
        values = parse_qs(urlsplit(parts[1]).query).get("token")
        if values:
            return values[0]
    for line in lines[1:]:
        name, _, value = line.partition(":")
        if name.strip().lower() == "authorization" and value.strip().lower().startswith("bearer "):
            return value.strip()[7:].strip()
    return ""


@dataclass
class GateStats:
    """Connections let through and refused."""

    accepted: int = 0
    refused: int = 0


class TokenGate:
    """Listens on *host*:*port*, checks the token, forwards to 127.0.0.1:*upstream_port*."""

    def __init__(self, *, host: str, port: int, upstream_port: int, token: str,
                 tls_cert: Path | None = None, tls_key: Path | None = None) -> None:
        self.host, self.port, self.upstream_port = host, port, upstream_port
        self._token = token.encode()
        self._ssl: ssl.SSLContext | None = None
        if tls_cert is not None:
            self._ssl = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
            try:
                self._ssl.load_cert_chain(tls_cert, tls_key)
            except (OSError, ssl.SSLError) as exc:
                raise GateError(f"{tls_cert}: cannot load the TLS certificate/key: {exc}") from None
        self.stats = GateStats()
        self._loop = asyncio.new_event_loop()
        self._server: asyncio.AbstractServer | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Bind (raising GateError on failure) and serve in a thread of its own."""
        try:
            self._server = self._loop.run_until_complete(
                asyncio.start_server(self._client, self.host, self.port, ssl=self._ssl))
        except OSError as exc:
            raise GateError(f"cannot listen on {self.host}:{self.port}: {exc.strerror}") from None
        self.port = self._server.sockets[0].getsockname()[1]
        self._thread = threading.Thread(target=self._loop.run_forever, name="foxglove-gate", daemon=True)
        self._thread.start()

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HEAD_TIMEOUT_S)
        except (asyncio.TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, ConnectionError):
            writer.close()
            return
        if len(head) > HEAD_LIMIT or not hmac.compare_digest(token_of(head).encode(), self._token):
            self.stats.refused += 1
            log.warning("Foxglove connection from %s refused: no valid token", peer)
            writer.write(b"HTTP/1.1 401 Unauthorized\r\nContent-Length: 0\r\nConnection: close\r\n\r\n")
            await _close(writer)
            return
        try:
            up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.upstream_port)
        except OSError:
            writer.close()
            return
        self.stats.accepted += 1
        up_writer.write(head)
        await asyncio.gather(_pipe(reader, up_writer), _pipe(up_reader, writer))

    def stop(self) -> None:
        """Stop listening and end the thread."""
        if self._server is not None:
            self._server.close()
        if self._thread is not None:
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout=2.0)


async def _pipe(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
    try:
        while data := await src.read(65536):
            dst.write(data)
            await dst.drain()
    except (ConnectionError, asyncio.IncompleteReadError, OSError):
        pass
    finally:
        await _close(dst)


async def _close(writer: asyncio.StreamWriter) -> None:
    try:
        writer.close()
        await writer.wait_closed()
    except (ConnectionError, OSError):
        pass
