"""Who may publish what on the bus: three roles and the channels each may sign (docs/security.md).

- *vehicle*: the services, signing with the bus key. Every channel but the pilot's.
- *operator*: a laptop or ground station, signing with an operator key (``u2sa key operator``).
  It uploads missions, stops services, reads and sets parameters, raises or clears a failsafe,
  and asks who is there; nothing else.
- *pilot*: the RC mux, signing with the pilot's Ed25519 key. Only the pilot's own channels,
  RC_MODE and MANUAL_CMD: the switch and the sticks. Nobody else may sign them, the services
  included, so the pilot's switch outranks every sender holding the bus key.

A packet signed by a key whose role may not publish its channel is dropped and counted as
``denied``. The table is here and nowhere else; docs/security.md prints it.
"""

from __future__ import annotations

from u2sa_hw import channels as ch

VEHICLE, OPERATOR, PILOT = "vehicle", "operator", "pilot"
ROLES = (VEHICLE, OPERATOR, PILOT)

PILOT_CHANNELS = frozenset({ch.RC_MODE, ch.MANUAL_CMD})
"""The pilot's decision: the mode switch, arming, the autonomy enable and the sticks."""

OPERATOR_CHANNELS = frozenset({ch.MISSION_CMD, ch.STOP, ch.CONFIG_REQUEST, ch.CONFIG_CHANGE,
                               ch.DISCOVERY_REQUEST, ch.FAILSAFE})
"""What a ground station sends: missions, stops, parameters, failsafe raise and clear, discovery."""

COMMAND_CHANNELS = frozenset({ch.MISSION_CMD, ch.STOP, ch.CONFIG_CHANGE, ch.FAILSAFE})
"""Commands a service obeys only when signed after it started (a failsafe raise excepted: it fails safe)."""


def may_publish(role: str, channel: str) -> bool:
    """True when a key of *role* may sign a message on *channel*."""
    if channel in PILOT_CHANNELS:
        return role == PILOT
    if role == VEHICLE:
        return True
    if role == OPERATOR:
        return channel in OPERATOR_CHANNELS
    return False


def table() -> list[tuple[str, str, str, str]]:
    """(channel, vehicle, operator, pilot) with "yes"/"no": the table docs/security.md prints."""
    rows = []
    for channel in sorted({*ch.BASE_TYPES, f"{ch.RAW_PREFIX}<device>"}):
        rows.append((channel, *("yes" if may_publish(role, channel) else "no" for role in ROLES)))
    return rows
