"""The Foxglove bridge as a service (kind ``foxglove_bridge``), so a vehicle can run it as a unit.

``u2sa foxglove`` runs the same service from the command line. It listens on 127.0.0.1
unless ``host`` says otherwise, and a non-loopback ``host`` needs a ``token_file`` holding
a token of 16 characters or more: :meth:`FoxgloveBridgeService.check_config` refuses
anything else, so ``u2sa check`` reports it and the service does not start (the SDK server
itself has no authentication; the token is checked by ``u2sa_hw.foxglove.gate``).

The settings that decide who can reach the bridge and what it may do (``host``, ``port``,
``token_file``, ``tls_cert``, ``tls_key``, ``allow_parameter_writes``) are ``remote=False``:
no Foxglove client and no ``u2sa param set`` can open the bridge to the network; they
change in the profile, with a restart. See docs/foxglove.md.
"""

from __future__ import annotations

import ipaddress
import ssl
from pathlib import Path
from typing import Any, ClassVar

from u2sa_hw.config.fields import ConfigError, field
from u2sa_hw.foxglove.gate import GateError, read_token
from u2sa_hw.service.contract import U2SAService
from u2sa_hw.profile.vehicle import Origin

LOOPBACK_NAMES = ("localhost", "ip6-localhost")
NO_ORIGIN = ("the profile has no [vehicle] origin: local positions are not on the map "
             "(add origin = { lat = ..., lon = ..., alt = ... } to [vehicle])")


def is_loopback(host: str) -> bool:
    """True for an address only this machine can reach."""
    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class FoxgloveBridgeService(U2SAService):
    """Serves every LCM channel, decoded, to Foxglove over a WebSocket."""

    SERVICE_TYPE: ClassVar[str] = "foxglove_bridge"
    CONFIG = (
        field("host", "127.0.0.1", "address to listen on; anything but loopback needs token_file", remote=False),
        field("port", 8765, "WebSocket port (0: any free port)", ge=0, le=65535, remote=False),
        field("token_file", "", "file holding the token clients must send (?token=...) when host is not loopback",
              remote=False, file="secret"),
        # The certificate is public, but a PEM given without tls_key holds the private key too: secret as well.
        field("tls_cert", "", "PEM certificate: the network listener speaks TLS (wss://)", remote=False,
              file="secret"),
        field("tls_key", "", "PEM private key of tls_cert", remote=False, file="secret"),
        field("queue_size", 5000, "messages buffered between the bus and the server; beyond, drops are counted",
              ge=1, le=1000000),
        field("allow_parameter_writes", False, "let Foxglove clients change service configs (signed ConfigChange)",
              remote=False),
        field("tail_logs", True, "send the service log lines of the profile's log_dir on /log"),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.host = str(self.config["host"]).strip() or "127.0.0.1"
        self.token_path = self._path("token_file")
        self.token = self._network_token()   # ConfigError (one line from the CLI) before anything opens
        self.bridge: Any = None
        self.gate: Any = None
        self.bus: Any = None

    def _path(self, field_name: str) -> Path | None:
        text = str(self.config[field_name])
        profile = getattr(self, "profile", None)   # `u2sa check` may run the checks without a profile
        if profile is not None:
            return profile.resolve_path(text)
        return Path(text.strip()).expanduser() if text.strip() else None

    def _network_token(self) -> str:
        """The token a network listener needs ("" on loopback); ConfigError naming the fix when it cannot be had."""
        host = str(self.config["host"]).strip() or "127.0.0.1"
        if is_loopback(host):
            return ""
        path = self._path("token_file")
        if path is None:
            raise ConfigError(f"{self.name}: host {host!r} would expose the bus to the network without "
                              "authentication: set token_file (u2sa foxglove --token-file FILE), or keep host = "
                              "\"127.0.0.1\" and reach it through an SSH tunnel (docs/foxglove.md)")
        try:
            token = read_token(path)
        except GateError as exc:
            raise ConfigError(f"{self.name}: {exc}") from None
        cert, key = self._path("tls_cert"), self._path("tls_key")
        if cert is None and key is not None:
            raise ConfigError(f"{self.name}: tls_key is set without tls_cert; set both or neither")
        if cert is not None:
            try:
                ssl.create_default_context(ssl.Purpose.CLIENT_AUTH).load_cert_chain(cert, key)
            except (OSError, ssl.SSLError) as exc:
                raise ConfigError(f"{self.name}: cannot load the TLS certificate {cert} (key {key or 'in it'}): "
                                  f"{exc}") from None
        return token

    def check_config(self) -> None:
        """Refuse a listener beyond loopback without a readable token of 16+ characters (``token_file``) or
        with a TLS certificate/key that does not load."""
        self._network_token()
        super().check_config()

    def origin(self) -> Origin | None:
        """The profile's origin, None when it declares none (no map of local positions then)."""
        return self.profile.origin if self.profile.raw.get("vehicle", {}).get("origin") else None

    def setup(self) -> None:
        """Start the server (and the token gate), then subscribe to the bus."""
        try:
            import foxglove  # noqa: F401 - the optional dependency, checked before anything starts
        except ModuleNotFoundError:
            raise RuntimeError("the Foxglove bridge needs the foxglove-sdk package: pip install 'u2sa-hw[foxglove]'") \
                from None
        from u2sa_hw.bus.client import BusClient
        from u2sa_hw.foxglove.bridge import FoxgloveBridge
        from u2sa_hw.foxglove.gate import TokenGate
        from u2sa_hw.foxglove.params import ParameterBridge

        c = self.config
        gated = not is_loopback(self.host)
        p = self.profile
        self.bus = BusClient(p.lcm_url, name=f"{self.name}-params", system_id=p.system_id, security=p.bus_security,
                             key_file=p.bus_key, interface=p.bus_interface)
        params = ParameterBridge(self.bus, allow_writes=bool(c["allow_parameter_writes"]), status=self._status,
                                 heard=lambda: list(self.bridge.mapper.health.services))
        if params.refused_open_bus:
            self.logger.warning("allow_parameter_writes is ignored: the bus is open, a change would not be signed")
        log_dir = p.log_dir if c["tail_logs"] else None
        self.bridge = FoxgloveBridge(self.transport, origin=self.origin(), port=0 if gated else int(c["port"]),
                                     queue_size=int(c["queue_size"]), log_dir=log_dir, listener=params,
                                     name=f"u2sa {p.name}")
        self.params = params
        if gated:
            self.gate = TokenGate(host=self.host, port=int(c["port"]), upstream_port=self.bridge.port,
                                  token=self.token, tls_cert=self._path("tls_cert"), tls_key=self._path("tls_key"))
            self.gate.start()
        self.bridge.start()
        if self.origin() is None:
            self.logger.warning("%s", NO_ORIGIN)
            self.last_error = NO_ORIGIN   # in its health too: `u2sa health` says why the Map stays empty
        self.logger.info("Foxglove: open %s", self.url)

    @property
    def url(self) -> str:
        """What to type into Foxglove's "Open connection" dialog."""
        if self.gate is not None:
            scheme = "wss" if self.gate._ssl is not None else "ws"
            return f"{scheme}://{self.host}:{self.gate.port}/?token=<the token in {self.token_path}>"
        return f"ws://127.0.0.1:{self.bridge.port}" if self.bridge is not None else ""

    def _status(self, level: str, text: str) -> None:
        import foxglove

        levels = {"info": foxglove.StatusLevel.Info, "warning": foxglove.StatusLevel.Warning,
                  "error": foxglove.StatusLevel.Error}
        self.logger.info("to Foxglove clients: %s", text)
        if self.bridge is not None:
            self.bridge.server.publish_status(text, levels.get(level, foxglove.StatusLevel.Info))

    def run(self) -> None:
        """Serve until stopped; degraded while messages are being dropped."""
        dropped = 0
        note = NO_ORIGIN if self.origin() is None else ""
        while self.wait(1.0):
            now = self.bridge.stats.dropped
            if now > dropped:
                self.status = "degraded"
                self.last_error = f"dropped {now - dropped} messages: the bridge cannot keep up (queue_size)"
            elif self.status == "degraded":
                self.status, self.last_error = "ok", note
            dropped = now

    def kill(self) -> None:
        """Stop the gate, the server and the parameter client."""
        for part in (self.gate, self.bridge, self.bus):
            if part is not None:
                try:
                    part.stop() if part is not self.bus else part.close()
                except Exception as exc:  # noqa: BLE001 - tearing down
                    self.logger.error("stopping the Foxglove bridge: %s", exc)
        super().kill()

    def health_details(self) -> dict[str, Any]:
        """Drops, queue depth, counts, clients let through and refused."""
        out: dict[str, Any] = self.bridge.describe() if self.bridge is not None else {}
        out["url"] = self.url
        if self.origin() is None:
            out["map"] = NO_ORIGIN
        if self.gate is not None:
            out["gate_accepted"], out["gate_refused"] = self.gate.stats.accepted, self.gate.stats.refused
        if getattr(self, "params", None) is not None:
            out["parameter_writes"], out["parameter_writes_refused"] = self.params.writes, self.params.refused
        return out
