"""The U2SA contract's requests a service answers over the bus: discovery, stop, config enumeration and change.

:class:`ContractRequests` is a part of :class:`~u2sa_hw.service.contract.U2SAService` (its base):
it subscribes the contract channels when the service is made, and answers ``DiscoveryRequest``
(name, type, status, the channels it publishes and takes), ``StopCommand`` (all, or by name),
``ConfigRequest`` (every field) and ``ConfigChange`` (one field, validated by the service's
configurator; a changed ``log_level`` applies at once). It uses the service's name, status,
publish/subscribe tables, configurator and logger.
"""

from __future__ import annotations

import os

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.config.fields import to_text
from u2sa_hw.service.health import HOSTNAME
from u2sa_hw.service.log import set_level


class ContractRequests:
    """The contract's bus requests, answered (mixed into U2SAService, whose state it reads)."""

    # -- contract messages over the bus -----------------------------------------------------
    def _contract_subscriptions(self) -> None:
        # Registered like any other channel, so discovery lists them from the first reply on.
        self.register_subscriber(ch.DISCOVERY_REQUEST, t.DiscoveryRequest, self._on_discovery)
        self.register_subscriber(ch.STOP, t.StopCommand, self._on_stop)
        self.register_subscriber(ch.CONFIG_REQUEST, t.ConfigRequest, self._on_config_request)
        self.register_subscriber(ch.CONFIG_CHANGE, t.ConfigChange, self._on_config_change)
        self.register_publisher(ch.DISCOVERY_RESPONSE, t.DiscoveryResponse)
        self.register_publisher(ch.CONFIG_RESPONSE, t.ConfigResponse)
        self.register_publisher(ch.HEALTH, t.Health)

    def _on_discovery(self, req: t.DiscoveryRequest) -> None:
        if (req.name_filter and req.name_filter != self.name) or not self.running:
            return   # not yet started (the duplicate probe pumps the transport before start()) or stopping
        resp = t.DiscoveryResponse()
        resp.request_id = req.request_id
        resp.name, resp.service_type, resp.status = self.name, self.SERVICE_TYPE, self.status
        resp.host, resp.pid = HOSTNAME, os.getpid()
        # dict() copies in one step: other threads may register channels meanwhile.
        resp.publishes = [_channel_info(c, ty) for c, ty in sorted(dict(self._publishers).items())]
        resp.num_publishes = len(resp.publishes)
        resp.subscribes = [_channel_info(c, ty) for c, ty in sorted(dict(self._subscribers).items())]
        resp.num_subscribes = len(resp.subscribes)
        self.publish(ch.DISCOVERY_RESPONSE, resp)

    def _on_stop(self, cmd: t.StopCommand) -> None:
        if cmd.all or cmd.name == self.name:
            self.logger.info("stop requested over the bus by %s", cmd.header.source or "?")
            self.stop()

    def _config_response(self, request_id: str, ok: bool, error: str, names: list[str]) -> t.ConfigResponse:
        resp = t.ConfigResponse()
        resp.request_id, resp.name, resp.ok, resp.error = request_id, self.name, ok, error
        fields = []
        for name, tname, value in self.config.enumerate():
            if name in names:
                f = t.ConfigField()
                f.name, f.type_name, f.value = name, tname, to_text(value)
                fields.append(f)
        resp.fields, resp.num_fields = fields, len(fields)
        return resp

    def _on_config_request(self, req: t.ConfigRequest) -> None:
        if req.target != self.name:
            return
        names = [n for n, _, _ in self.config.enumerate()]
        self.publish(ch.CONFIG_RESPONSE, self._config_response(req.request_id, True, "", names))

    def _on_config_change(self, req: t.ConfigChange) -> None:
        if req.target != self.name:
            return
        ok, reason = self.config.try_set(req.field, req.value)
        self.publish(ch.CONFIG_RESPONSE, self._config_response(req.request_id, ok, reason, [req.field]))
        if ok:
            try:
                if req.field == "log_level":
                    set_level(self.log_level_name())
                    self.logger.info("log level is now %s", self.log_level_name())
                self.on_config_change(req.field, self.config.get(req.field))
            except Exception as exc:  # noqa: BLE001 - a bad live change must not kill the service
                self.error(f"applying config change {req.field} failed: {exc}")


def _channel_info(channel: str, type_name_: str) -> t.ChannelInfo:
    info = t.ChannelInfo()
    info.channel, info.type_name = channel, type_name_
    return info
