"""The RC mux's health details, read from its state (docs/drivers-gpio-rc.md lists them)."""

from __future__ import annotations

from typing import Any

from u2sa_hw.drivers.rc_mux.state import MuxState


def health_details(state: MuxState, *, at_ns: int, manual_commands: int = 0) -> dict[str, Any]:
    """Mode, line and why, arming, failsafes, pre-arm, counters, read-back, and each channel's width as of
    *at_ns* (the device clock; the host's before it started)."""
    g, rb, f, meter = state.gate, state.readback, state.filter, state.meter
    allowed, why = state.autonomy_allowed()
    details: dict[str, Any] = {
        "mode": f.mode_name, "autonomy_enabled": g.enabled, "enable_blocked_by": "" if allowed else why,
        "armed": g.armed, "hold": g.hold, "failsafe": g.failsafes.active,
        "failsafe_sources": ",".join(sorted(g.failsafes.held())),
        "prearm_failed": "; ".join(x.reason for x in g.prearm_failures), "checks_lost": g.checks_lost,
        "stalls": state.loop.stalls, "timed_skipped": state.clock.skipped, "manual_commands": manual_commands,
        "select_readback": "none" if rb.level is None else rb.level, "select_mismatch": rb.mismatch,
        "select_mismatches": rb.mismatches, "mode_frames": f.frames, "mode_changes": f.changes,
        "signal_losses": state.signal_losses, "enable_changes": g.enable_changes, "pulses": meter.pulses,
        "rejected": meter.rejected_total,
        "rejected_kinds": ",".join(f"{k}:{n}" for k, n in sorted(meter.rejected.items())),
    }
    for name, width in zip(state.channels, state.widths.as_of(at_ns)):
        details[f"{name}_us"] = width
    return details
