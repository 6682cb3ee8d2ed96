"""One row per service from the bus's health messages: what Foxglove's Table panel and
``u2sa health --watch`` show.

The HSM's ``SystemHealth`` gives each service's state as the HSM sees it (restarts,
heartbeat and data age, the reason); each service's own ``Health`` gives its status,
CPU, memory, drops, the failsafe raises it accepted though stale or foreign (added to the
reason) and message counters, from which the rates are the difference of two
successive messages over the service's uptime between them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass
class _Seen:
    health: Any
    rx: int
    tx: int
    uptime_s: float
    rx_hz: float = 0.0
    tx_hz: float = 0.0


@dataclass
class HealthTable:
    """The latest health of every service heard, with its message rates."""

    services: dict[str, _Seen] = field(default_factory=dict)
    system: Any = None

    def on_health(self, msg: Any) -> None:
        """Take one service's ``Health``."""
        rx = sum(c.messages for c in msg.channels if c.direction == "in")
        tx = sum(c.messages for c in msg.channels if c.direction == "out")
        cur = _Seen(msg, rx, tx, msg.uptime_s)
        prev = self.services.get(msg.name)
        if prev is not None:
            dt = msg.uptime_s - prev.uptime_s
            if dt > 0 and rx >= prev.rx and tx >= prev.tx:   # a restart resets the counters: keep the old rate
                cur.rx_hz, cur.tx_hz = (rx - prev.rx) / dt, (tx - prev.tx) / dt
            else:
                cur.rx_hz, cur.tx_hz = prev.rx_hz, prev.tx_hz
        self.services[msg.name] = cur

    def on_system(self, msg: Any) -> None:
        """Take the HSM's ``SystemHealth``."""
        self.system = msg

    def rows(self) -> list[dict[str, Any]]:
        """A row per service: the HSM's services in its order, then those only heard from themselves."""
        states = {s.name: s for s in self.system.services} if self.system is not None else {}
        names = list(states) + sorted(n for n in self.services if n not in states)
        out = []
        for name in names:
            st, seen = states.get(name), self.services.get(name)
            h = seen.health if seen else None
            reason = _reason(st, h)
            out.append({
                "name": name,
                "state": st.state if st is not None else (h.status if h is not None else "?"),
                "status": h.status if h is not None else "",
                "reason": reason,
                "restarts": st.restarts if st is not None else 0,
                "rx_hz": round(seen.rx_hz, 1) if seen else None,
                "tx_hz": round(seen.tx_hz, 1) if seen else None,
                "cpu_percent": round(h.cpu_percent, 1) if h is not None else None,
                "rss_mb": round(h.rss_bytes / 1e6, 1) if h is not None else None,
                "dropped": int(h.dropped + h.malformed) if h is not None else None,
                "heartbeat_age_s": round(st.heartbeat_age_s, 2) if st is not None and st.heartbeat_age_s >= 0 else None,
            })
        return out

    def message(self) -> dict[str, Any]:
        """The table as one JSON-ready message (``u2sa.HealthTable``)."""
        sysh = self.system
        # Without an HSM no one counts the failsafes held: null (unknown), never "off"
        return {"failsafe": bool(sysh.failsafe) if sysh is not None else None,
                "summary": sysh.summary if sysh is not None else "no HSM heard (no U2SA_SYSTEM_HEALTH)",
                "services": self.rows()}


def _reason(state: Any, health: Any) -> str:
    """Why a service is not ok, in the words ``u2sa health`` uses (``u2sa_hw.service.health``); its last error when ok.

    The failsafe raises it accepted though stale or foreign follow, whatever its state
    (``bus_raises_accepted``, ``u2sa_hw.service.bus_handlers.raise_note``).
    """
    from u2sa_hw.service.health import health_reason, join_reasons
    from u2sa_hw.service.bus_handlers import parse_raises, raise_note

    details = {kv.key: kv.value for kv in health.details} if health is not None else {}
    raises = "; ".join(raise_note(e) for e in parse_raises(details.get("bus_raises_accepted", "")))
    own = health_reason(details, health.last_error) if health is not None else ""
    hsm = state.last_error if state is not None else ""
    if (state.state if state is not None else health.status) == "ok":
        return join_reasons(hsm or (health.last_error if health is not None else ""), raises)
    return join_reasons(hsm, own, raises)


_CELL_NUM = {"type": ["number", "null"]}
SCHEMA: dict[str, Any] = {
    "title": "u2sa.HealthTable", "type": "object",
    "properties": {
        "failsafe": {"type": ["boolean", "null"], "description": "held by any source, as the HSM counts them; "
                                                                   "null without an HSM"},
        "summary": {"type": "string"},
        "services": {"type": "array", "items": {
            "type": "object",
            "properties": {"name": {"type": "string"}, "state": {"type": "string"}, "status": {"type": "string"},
                           "reason": {"type": "string"}, "restarts": {"type": "integer"}, "rx_hz": _CELL_NUM,
                           "tx_hz": _CELL_NUM, "cpu_percent": _CELL_NUM, "rss_mb": _CELL_NUM,
                           "dropped": {"type": ["integer", "null"]}, "heartbeat_age_s": _CELL_NUM},
            "required": ["name", "state", "status", "reason", "restarts"]}}},
    "required": ["failsafe", "summary", "services"]}
