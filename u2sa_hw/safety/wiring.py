"""Check the ``[safety]`` table against the profile's services, before anything starts.

:func:`check_wiring` resolves every enabled service's kind (through the registry, as
``u2sa service`` does), asks each actuator service which actuator names it answers to
(``Actuator.declared_actuators``) and reads the RC channels of the ``rc_mux`` service; then
a mixer that names an actuator no service has, a hardware-mux output that is not a PWM
output, an RC channel the receiver does not have, or a manual mixer with no RC service is
one line naming the file, the key and the fix. ``u2sa run``, ``u2sa sim``, ``u2sa install``
and the rc_mux service call it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Mapping

from u2sa_hw.safety.config import SafetyConfig, load_safety
from u2sa_hw.profile.vehicle import ProfileError, VehicleProfile

RC_KIND = "rc_mux"
PWM_KINDS = frozenset({"pwm_servo"})   # outputs that can physically pass through a hardware RC mux

_quiet = logging.getLogger("u2sa_hw.safety.wiring")
_quiet.addHandler(logging.NullHandler())
_quiet.propagate = False


@dataclass(frozen=True)
class Wiring:
    """What the profile's services provide: actuator name -> (service, kind), RC channel names."""

    actuators: Mapping[str, tuple[str, str]]
    rc_service: str | None
    rc_channels: tuple[str, ...]


def rc_channel_names(text: str) -> tuple[str, ...]:
    """The channel names of an rc_mux ``channels`` value (``"throttle=5,steering=6,mode=13"``)."""
    names = []
    for item in str(text).split(","):
        if "=" in item:
            names.append(item.split("=", 1)[0].strip())
    return tuple(n for n in names if n)


def profile_wiring(profile: VehicleProfile) -> Wiring:
    """Collect the actuators and RC channels of every enabled service of *profile*."""
    from u2sa_hw.abstract import Actuator
    from u2sa_hw.config.configurator import Configurator
    from u2sa_hw.config.fields import ConfigError
    from u2sa_hw.registry import NOT_ACTUATOR_KINDS, resolve_kind
    from u2sa_hw.service.base_config import BASE_CONFIG

    actuators: dict[str, tuple[str, str]] = {}
    rc_service, rc_channels = None, ()
    for name, spec in profile.services.items():
        if not spec.enabled or spec.kind in NOT_ACTUATOR_KINDS:
            continue
        try:
            cls = resolve_kind(spec.kind)
        except LookupError as exc:
            raise ProfileError(f"{profile.path} [services.{name}]: {exc}") from None
        if not (isinstance(cls, type) and (issubclass(cls, Actuator) or spec.kind == RC_KIND)):
            continue
        try:
            config = Configurator(spec.config_path, (*BASE_CONFIG, *cls.config_fields()), logger=_quiet,
                                  initial=spec.settings, initial_source=f"{profile.path} [services.{name}] settings")
            values = {field_name: value for field_name, _t, value in config.enumerate()}
        except ConfigError as exc:
            raise ProfileError(str(exc)) from None
        if spec.kind == RC_KIND:
            rc_service, rc_channels = name, rc_channel_names(values.get("channels", ""))
            continue
        try:
            names = cls.declared_actuators(name, values)
        except (ConfigError, ValueError) as exc:
            raise ProfileError(f"{profile.path} [services.{name}]: {exc}") from None
        for actuator in names:
            if actuator in actuators:
                other = actuators[actuator][0]
                raise ProfileError(f"{profile.path} [services.{name}]: actuator '{actuator}' is also service "
                                   f"'{other}''s; every actuator name must be unique")
            actuators[actuator] = (name, spec.kind)
    return Wiring(actuators, rc_service, rc_channels)


def check_wiring(profile: VehicleProfile, safety: SafetyConfig | None = None) -> SafetyConfig:
    """The profile's safety table, checked against its services; ProfileError names file, key and fix."""
    from u2sa_hw.safety.prearm_table import parse_prearm

    safety = safety if safety is not None else load_safety(profile)
    parse_prearm(profile)  # the pre-arm table's own checks (services named, keys, types)
    where = f"{profile.path or 'the vehicle profile'} [safety]"
    wiring = profile_wiring(profile)
    known = ", ".join(sorted(wiring.actuators)) or "none"
    for actuator, channel in safety.hardware_mux.items():
        if actuator not in wiring.actuators:
            raise ProfileError(f"{where} hardware_mux: no service has an actuator '{actuator}' (actuators: {known})")
        service, kind = wiring.actuators[actuator]
        if kind not in PWM_KINDS:
            raise ProfileError(f"{where} hardware_mux: '{actuator}' is a {kind} output (service '{service}'); a "
                               "hardware RC mux switches only PWM wires, so remove it: the software mux covers it")
        _check_channel(wiring, channel, f"{where} hardware_mux.{actuator}")
    mixer = safety.manual_mixer
    if mixer is not None:
        for role, actuator in mixer.outputs.items():
            if actuator not in wiring.actuators:
                raise ProfileError(f"{where}.manual_mixer: {role} = '{actuator}' is not an actuator of any service "
                                   f"(actuators: {known}); name the actuator the pilot drives")
            if actuator in safety.hardware_mux:
                raise ProfileError(f"{where}.manual_mixer: {role} = '{actuator}' is wired through the hardware "
                                   "mux (hardware_mux), so the pilot drives it by wire; leave it out of the mixer")
        for key in ("throttle_channel", "steering_channel"):
            _check_channel(wiring, getattr(mixer, key), f"{where}.manual_mixer {key}")
    return safety


def _check_channel(wiring: Wiring, channel: str, where: str) -> None:
    if wiring.rc_service is None:
        raise ProfileError(f"{where}: the profile has no rc_mux service, so there is no RC channel '{channel}'; "
                           "add [services.rc] with kind = \"rc_mux\"")
    if channel not in wiring.rc_channels:
        raise ProfileError(f"{where}: '{channel}' is not a channel of the RC receiver (service "
                           f"'{wiring.rc_service}' channels: {', '.join(wiring.rc_channels) or 'none'})")
