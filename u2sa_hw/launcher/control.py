"""The launcher's control interface: a Unix stream socket speaking one JSON line each way.

Why a socket and not LCM: only processes on this board (with access to the profile's
``data_dir``) may restart services; the caller gets a definite answer or a definite
"no launcher here" (connection refused), never a timeout; and a second ``u2sa run`` on
the same vehicle finds the first one and refuses to start.

Requests (one JSON object per connection, newline-terminated):

- ``{"op": "status"}`` -> ``{"ok": true, "services": [ProcessStatus...]}``
- ``{"op": "restart", "service": "gps", "reason": "no heartbeat"}`` -> ``{"ok": true, "service": {...}}``
- ``{"op": "stop", "service": "gps"}`` / ``{"op": "start", "service": "gps"}``

Errors come back as ``{"ok": false, "error": "..."}``.
"""

from __future__ import annotations

import errno
import json
import os
import socket
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

if TYPE_CHECKING:
    from u2sa_hw.launcher.launcher import Launcher

SOCKET_NAME = "launcher.sock"
SOCKET_ENV = "U2SA_LAUNCHER_SOCKET"
MAX_REQUEST = 64 * 1024
_SUN_PATH_MAX = 107


class LauncherError(RuntimeError):
    """The launcher cannot be reached or refused a request; the message says which and why."""


class LauncherBusy(LauncherError):
    """Another launcher already owns the control socket of this vehicle."""


def default_socket_path(data_dir: Path) -> Path:
    """Where the launcher of a profile with *data_dir* listens."""
    return Path(data_dir) / SOCKET_NAME


Handler = Callable[[dict[str, Any]], dict[str, Any]]


class ControlServer:
    """The listening socket and its connections; the launcher's loop drives it via a selector."""

    def __init__(self, path: Path, handler: Handler) -> None:
        self.path = Path(path)
        self.handler = handler
        if len(os.fsencode(str(self.path))) > _SUN_PATH_MAX:
            raise LauncherError(f"control socket path {self.path} is longer than {_SUN_PATH_MAX} bytes; "
                                "set a shorter data_dir in the vehicle profile")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._claim_path()
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        old_umask = os.umask(0o177)   # owner only: whoever may restart services owns the data_dir
        try:
            self.sock.bind(str(self.path))
        finally:
            os.umask(old_umask)
        self.sock.listen(16)
        self.sock.setblocking(False)
        self._buffers: dict[socket.socket, bytes] = {}

    def _claim_path(self) -> None:
        if not self.path.exists():
            return
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        probe.settimeout(1.0)
        try:
            probe.connect(str(self.path))
        except OSError as exc:
            if exc.errno not in (errno.ECONNREFUSED, errno.ENOTSOCK, errno.ENOENT):
                raise LauncherError(f"cannot check control socket {self.path}: {exc}") from None
            self.path.unlink(missing_ok=True)   # left over from a launcher that died
            return
        finally:
            probe.close()
        raise LauncherBusy(f"another launcher is already running this vehicle (control socket {self.path}); "
                           "stop it first, or use a profile with another data_dir")

    def accept(self) -> socket.socket | None:
        """Accept one pending connection (non-blocking); the caller registers it for reading."""
        try:
            conn, _ = self.sock.accept()
        except (BlockingIOError, InterruptedError):
            return None
        conn.setblocking(False)
        self._buffers[conn] = b""
        return conn

    def readable(self, conn: socket.socket) -> bool:
        """Read from *conn*; answer once a whole line arrived. True when *conn* is done: unregister it,
        then :meth:`drop` it."""
        try:
            chunk = conn.recv(65536)
        except (BlockingIOError, InterruptedError):
            return False
        except OSError:
            chunk = b""
        data = self._buffers.get(conn, b"") + chunk
        if b"\n" not in data and chunk and len(data) <= MAX_REQUEST:
            self._buffers[conn] = data
            return False
        line = data.split(b"\n", 1)[0]
        if line.strip():
            reply = self._answer(line) if len(line) <= MAX_REQUEST else \
                {"ok": False, "error": f"request longer than {MAX_REQUEST} bytes"}
            try:
                conn.setblocking(True)
                conn.settimeout(1.0)
                conn.sendall(json.dumps(reply).encode() + b"\n")
            except OSError:
                pass   # the client went away; nothing to tell it
        return True

    def _answer(self, line: bytes) -> dict[str, Any]:
        try:
            request = json.loads(line)
        except ValueError as exc:
            return {"ok": False, "error": f"not JSON: {exc}"}
        if not isinstance(request, dict) or not isinstance(request.get("op"), str):
            return {"ok": False, "error": 'a request is a JSON object with "op" (status, restart, stop, start)'}
        try:
            return self.handler(request)
        except Exception as exc:  # noqa: BLE001 - a bad request must not take the launcher down
            return {"ok": False, "error": f"{type(exc).__name__}: {exc}"}

    def drop(self, conn: socket.socket) -> None:
        """Forget and close *conn*."""
        self._buffers.pop(conn, None)
        conn.close()

    def close(self) -> None:
        """Close every connection and remove the socket file."""
        for conn in list(self._buffers):
            self.drop(conn)
        self.sock.close()
        self.path.unlink(missing_ok=True)


def answer(launcher: Launcher, request: dict[str, Any]) -> dict[str, Any]:
    """The reply to one control request (op status, restart, stop or start) from *launcher*."""
    op = request["op"]
    if op == "status":
        return {"ok": True, "services": [s.as_dict() for s in launcher.status()]}
    name = request.get("service")
    if not isinstance(name, str):
        return {"ok": False, "error": f'"{op}" needs "service": NAME'}
    if op == "restart":
        reason = str(request.get("reason") or "requested over the control socket")
        return {"ok": True, "service": launcher.restart(name, reason=reason).as_dict()}
    if op == "stop":
        return {"ok": True, "service": launcher.stop_service(name).as_dict()}
    if op == "start":
        return {"ok": True, "service": launcher.start_service(name).as_dict()}
    return {"ok": False, "error": f"unknown op '{op}' (status, restart, stop, start)"}


class LauncherClient:
    """Talks to a running launcher's control socket."""

    def __init__(self, path: Path | str, *, timeout: float = 3.0) -> None:
        self.path = Path(path)
        self.timeout = timeout

    def request(self, op: str, **fields: Any) -> dict[str, Any]:
        """Send one request; return the reply. LauncherError when unreachable or refused."""
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        sock.settimeout(self.timeout)
        try:
            sock.connect(str(self.path))
            sock.sendall(json.dumps({"op": op, **fields}).encode() + b"\n")
            data = b""
            while not data.endswith(b"\n"):
                chunk = sock.recv(65536)
                if not chunk:
                    break
                data += chunk
        except FileNotFoundError:
            raise LauncherError(f"no launcher: {self.path} does not exist (is 'u2sa run' running?)") from None
        except ConnectionRefusedError:
            raise LauncherError(f"no launcher listens on {self.path} (it died; start 'u2sa run' again)") from None
        except OSError as exc:
            raise LauncherError(f"launcher at {self.path}: {exc}") from None
        finally:
            sock.close()
        try:
            reply = json.loads(data)
        except ValueError:
            raise LauncherError(f"launcher at {self.path} sent no valid answer ({data[:80]!r})") from None
        if not reply.get("ok"):
            raise LauncherError(f"launcher refused {op}: {reply.get('error', 'no reason given')}")
        return reply

    def status(self) -> list[dict[str, Any]]:
        """Every supervised service's status."""
        return list(self.request("status")["services"])

    def restart(self, service: str, *, reason: str = "") -> dict[str, Any]:
        """Restart *service* (a stop then a start; a failed one gets a fresh start)."""
        return dict(self.request("restart", service=service, reason=reason)["service"])

    def available(self) -> bool:
        """True when a launcher answers on the socket."""
        try:
            self.request("status")
        except LauncherError:
            return False
        return True
