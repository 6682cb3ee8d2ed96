"""``[safety]`` for ``u2sa check``: every problem of the table, not only the first.

The safety modules stop at the first mistake (they guard ``u2sa run`` and the rc_mux
service, where one is enough to refuse). The check asks them one part at a time so that
each part's problem is its own line: every top-level key of ``[safety]`` alone
(:func:`~u2sa_hw.safety.config.parse_safety`), every check of ``[safety.prearm]`` alone
(:func:`~u2sa_hw.safety.prearm_table.parse_prearm`), then the wiring against the services
(:func:`~u2sa_hw.safety.wiring.check_wiring`) for each ``hardware_mux`` output, each
manual-mixer actuator and the mixer's stick channels. The table is read from the profile as
written (*raw*), so a lenient copy of the profile that could not keep it still gets it checked.
"""

from __future__ import annotations

import dataclasses
from types import MappingProxyType
from typing import Any, Callable, Mapping

from u2sa_hw.check.problem import Collector

FIX = "see docs/safety.md"


def check_safety(profile: Any, raw: Any, out: Collector) -> None:
    """Add every problem of the ``[safety]`` table *raw* (as written) of *profile* to *out*."""
    from u2sa_hw.safety.config import SafetyConfig, parse_safety

    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        return   # "'safety' must be a table": reported with the top-level tables
    where = f"{profile.path or 'the vehicle profile'} [safety]"
    good: dict[str, Any] = {}
    for key, value in raw.items():
        if _report(lambda: parse_safety({key: value}, where=where), out):
            good[key] = value
    safety = parse_safety(good, where=where)
    if isinstance(raw.get("prearm"), dict):
        for key, value in raw["prearm"].items():
            _report(lambda: _parse_prearm(profile, {key: value}), out)
    _check_wiring(profile, safety, out, empty=SafetyConfig())


def _check_wiring(profile: Any, safety: Any, out: Collector, *, empty: Any) -> None:
    """Each hardware-mux output, each mixer actuator and the stick channels against the services."""
    bare = dataclasses.replace(profile, raw={**profile.raw, "safety": {}})   # prearm: checked above
    mux_ok: dict[str, str] = {}
    for actuator, channel in safety.hardware_mux.items():
        part = dataclasses.replace(empty, hardware_mux=MappingProxyType({actuator: channel}))
        if _report(lambda: _wiring(bare, part), out, wiring=True):
            mux_ok[actuator] = channel
    mixer = safety.manual_mixer
    if mixer is None:
        return
    mux = MappingProxyType(mux_ok)
    parts = [dataclasses.replace(mixer, outputs=MappingProxyType({role: actuator}))
             for role, actuator in mixer.outputs.items()]
    parts.append(dataclasses.replace(mixer, outputs=MappingProxyType({})))   # the channels on their own
    for one in parts:
        part = dataclasses.replace(empty, hardware_mux=mux, manual_mixer=one)
        _report(lambda: _wiring(bare, part), out, wiring=True)


def _wiring(profile: Any, safety: Any) -> None:
    from u2sa_hw.safety.wiring import check_wiring

    check_wiring(profile, safety)


def _parse_prearm(profile: Any, table: Mapping[str, Any]) -> None:
    from u2sa_hw.safety.prearm_table import parse_prearm

    parse_prearm(dataclasses.replace(profile, raw={**profile.raw, "safety": {"prearm": dict(table)}}))


def _report(check: Callable[[], Any], out: Collector, *, wiring: bool = False) -> bool:
    """Run *check*; add its error (each line of it) to *out* and return False when it fails."""
    from u2sa_hw.config.fields import ConfigError
    from u2sa_hw.profile.vehicle import ProfileError

    try:
        check()
    except (ProfileError, ConfigError) as exc:
        text = str(exc)
        if wiring and "[safety" not in text:
            # the services could not be read: a service's own error above is why
            if any(p.is_error and p.key.startswith("services.") for p in out.problems):
                return False
        left_out = wiring and any(p.is_error and p.key.endswith(".kind") for p in out.problems)
        fix = FIX + (" (the services with an unknown kind above were left out of this check)" if left_out else "")
        for line in text.splitlines():
            if line.strip():
                out.from_text(line, key="safety", fix=fix)
        return False
    return True
