"""A mock ODrive axis's configuration, its firmware build and the endpoints that reach it over CAN.

``OdriveConfig`` is what save_configuration would have stored and a reboot restores,
including the watchdog (``watchdog_timeout``/``enable_watchdog``). With firmware 0.6 a driver
reaches configuration fields by RxSdo/TxSdo through endpoint ids, which belong to one firmware
build: ENDPOINTS is this mock's own flat_endpoints table for its build MOCK_FW (an unreleased
0.6.10, so ids written for the mock are refused against a real release), not a real release's
ids. ``endpoint_access`` carries out one RxSdo on a configuration, as mock_devices/odrive_node.py
does for every RxSdo frame it receives.
"""

from __future__ import annotations

import dataclasses

from u2sa_hw.protocols import odrive_cansimple as cs
from u2sa_hw.protocols.odrive_cansimple import ControlMode, InputMode

# an unreleased build, so endpoint ids written for this mock are refused by a real 0.6.10
VERSION_06 = cs.Version(protocol=2, hw_major=3, hw_minor=6, hw_variant=56, fw_major=0, fw_minor=6,
                        fw_revision=10, fw_unreleased=1)
MOCK_FW = cs.version_text(VERSION_06)
WATCHDOG_TIMEOUT_ENDPOINT = 0x2F0
ENABLE_WATCHDOG_ENDPOINT = 0x2F1
# endpoint id -> (OdriveConfig field, endpoint type)
ENDPOINTS: dict[int, tuple[str, str]] = {
    WATCHDOG_TIMEOUT_ENDPOINT: ("watchdog_timeout", "float"),
    ENABLE_WATCHDOG_ENDPOINT: ("enable_watchdog", "bool"),
    0x2F2: ("vel_limit", "float"),
}


@dataclasses.dataclass
class OdriveConfig:
    """The axis configuration a reboot restores (what save_configuration would have stored)."""

    node_id: int
    control_mode: int = ControlMode.POSITION_CONTROL
    input_mode: int = InputMode.PASSTHROUGH
    vel_limit: float = 2.0  # rev/s
    current_limit: float = 10.0  # A
    vel_ramp_rate: float = 1.0  # rev/s^2
    pos_gain: float = 20.0  # (rev/s)/rev
    vel_gain: float = 0.1667
    vel_integrator_gain: float = 0.3333
    traj_vel_limit: float = 2.0
    traj_accel_limit: float = 0.5
    traj_decel_limit: float = 0.5
    traj_inertia: float = 0.0
    watchdog_timeout: float = 0.0  # s (axis.config.watchdog_timeout)
    enable_watchdog: bool = False


def endpoint_access(config: OdriveConfig, opcode: int, endpoint: int, raw: bytes, *, frozen: bool,
                    node_name: str) -> bytes | None:
    """Carry out one RxSdo on *config*: a write sets the endpoint's field (unless *frozen*: then
    it is silently not applied) and returns None; a read returns the TxSdo reply's payload.
    CanSimpleError naming *node_name* for an endpoint id this build does not have."""
    entry = ENDPOINTS.get(endpoint)
    if entry is None:
        raise cs.CanSimpleError(f"{node_name}: no endpoint {endpoint} in this firmware build ({MOCK_FW})")
    field, kind = entry
    if opcode == cs.SDO_WRITE:
        if not frozen:
            setattr(config, field, cs.sdo_value(kind, raw))
        return None
    return cs.encode_tx_sdo(endpoint, kind, getattr(config, field))
