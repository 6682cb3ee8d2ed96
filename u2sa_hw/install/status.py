"""``u2sa status``: each unit's state as systemd sees it, next to the HSM's view.

systemd's side comes from ``systemctl show`` (active/sub state, restarts, main PID,
result, the service's STATUS= text). The HSM's side is the latest ``SystemHealth`` on
``U2SA_SYSTEM_HEALTH`` (state, restarts, last error, data age per service); when none
arrives within the timeout, the report says so instead of guessing.
"""

from __future__ import annotations

import subprocess
import threading
from dataclasses import asdict, dataclass, field
from typing import Any

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.install.units import HSM_UNIT, TARGET, service_units
from u2sa_hw.profile.vehicle import VehicleProfile

SHOW_PROPERTIES = ("Id", "LoadState", "ActiveState", "SubState", "NRestarts", "MainPID", "Result",
                   "StatusText", "UnitFileState")


@dataclass
class UnitState:
    """One unit as systemd reports it (empty strings when systemd could not be asked)."""

    unit: str
    service: str = ""
    load: str = ""
    active: str = ""
    sub: str = ""
    restarts: str = ""
    main_pid: str = ""
    result: str = ""
    status_text: str = ""
    enabled: str = ""
    hsm: dict[str, Any] = field(default_factory=dict)


def systemctl_show(units: list[str], *, systemctl: str = "systemctl") -> tuple[list[dict[str, str]], str]:
    """``systemctl show`` of *units*: one property dict per unit, and an error text ('' when fine)."""
    cmd = [systemctl, "show", "--no-pager", f"--property={','.join(SHOW_PROPERTIES)}", *units]
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=15)
    except FileNotFoundError:
        return [], f"{systemctl} not found (is this a systemd system?)"
    except subprocess.TimeoutExpired:
        return [], f"{' '.join(cmd)} timed out"
    if done.returncode != 0:
        return [], (done.stderr.strip() or f"systemctl show exited {done.returncode}")
    blocks: list[dict[str, str]] = []
    for block in done.stdout.strip().split("\n\n"):
        props = dict(line.split("=", 1) for line in block.splitlines() if "=" in line)
        blocks.append(props)
    return blocks, ""


def listen_system_health(url: str | None, *, timeout: float) -> t.SystemHealth | None:
    """The first SystemHealth published within *timeout* seconds, or None."""
    from u2sa_hw.bus.client import BusClient

    got: list[t.SystemHealth] = []
    event = threading.Event()

    def on_health(_channel: str, msg: Any) -> None:
        if isinstance(msg, t.SystemHealth) and not got:
            got.append(msg)
            event.set()

    with BusClient(url) as client:
        sub = client.transport.subscribe(ch.SYSTEM_HEALTH, t.SystemHealth, on_health)
        event.wait(timeout)
        client.transport.unsubscribe(sub)
    return got[0] if got else None


def collect_status(profile: VehicleProfile, *, timeout: float = 2.5,
                   systemctl: str = "systemctl") -> dict[str, Any]:
    """The whole status report as a JSON-able dict: units, HSM view, and what could not be read."""
    units = service_units(profile)
    names = [TARGET, "u2sa-multicast-lo.service", *(u.unit for u in units)]
    if HSM_UNIT not in names:
        names.append(HSM_UNIT)
    by_unit = {u.unit: u.name for u in units}
    blocks, systemd_error = systemctl_show(names, systemctl=systemctl)
    states: list[UnitState] = []
    by_id = {b.get("Id", ""): b for b in blocks}
    for unit in names:
        props = by_id.get(unit, {})
        states.append(UnitState(
            unit=unit, service=by_unit.get(unit, ""), load=props.get("LoadState", ""),
            active=props.get("ActiveState", ""), sub=props.get("SubState", ""),
            restarts=props.get("NRestarts", ""), main_pid=props.get("MainPID", ""),
            result=props.get("Result", ""), status_text=props.get("StatusText", ""),
            enabled=props.get("UnitFileState", "")))
    health = listen_system_health(profile.lcm_url, timeout=timeout)
    hsm_note = ""
    if health is None:
        hsm_note = (f"no SystemHealth on {ch.SYSTEM_HEALTH} within {timeout:g} s: the HSM is not running or "
                    f"not reachable (systemctl status {HSM_UNIT})")
    else:
        seen = {s.name: s for s in health.services}
        for st in states:
            hs = seen.get(st.service)
            if hs is not None:
                st.hsm = {"state": hs.state, "restarts": hs.restarts, "last_error": hs.last_error,
                          "heartbeat_age_s": round(hs.heartbeat_age_s, 2), "data_age_s": round(hs.data_age_s, 2)}
    return {
        "units": [asdict(s) for s in states],
        "systemd_error": systemd_error,
        "hsm": None if health is None else {"failsafe": health.failsafe, "summary": health.summary},
        "hsm_note": hsm_note,
    }


def format_status(report: dict[str, Any]) -> str:
    """The report as the table ``u2sa status`` prints."""
    lines = [f"{'UNIT':32} {'SYSTEMD':20} {'RESTARTS':>8}  {'HSM':12} {'HSM RESTARTS':>12}  LAST ERROR / STATUS"]
    for u in report["units"]:
        sd = f"{u['active']}/{u['sub']}" if u["active"] else "?"
        hsm = u["hsm"]
        detail = (hsm.get("last_error") if hsm else "") or u["status_text"]
        lines.append(f"{u['unit']:32} {sd:20} {u['restarts'] or '-':>8}  {hsm.get('state', '-') if hsm else '-':12} "
                     f"{hsm.get('restarts', '-') if hsm else '-':>12}  {detail}")
    if report["systemd_error"]:
        lines.append(f"systemd: {report['systemd_error']}")
    if report["hsm"] is not None:
        failsafe = "FAILSAFE" if report["hsm"]["failsafe"] else "no failsafe"
        lines.append(f"HSM: {failsafe}; {report['hsm']['summary']}")
    else:
        lines.append(f"HSM: {report['hsm_note']}")
    return "\n".join(lines)
