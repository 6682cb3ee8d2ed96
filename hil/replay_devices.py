"""Mock devices that play recorded raw I/O back to the real drivers: their interface and the serial one's factory.

Each device stands at the address the replay writes into its driver's config and is fed
the recorded ``RAW.<device>`` records by the player (hil/player.py). Each port kind names its
replay device's factory (``PortKind.replay``, :data:`u2sa_hw.ports.kinds.PORT_KINDS`):

- serial: :class:`~u2sa_hw.ports.serial.replay.ReplaySerialDevice` (a stamped pty), in its kind's
  package since it needs nothing from ``hil``; :func:`make_serial_device` here makes it with its
  driver's declared ``burst_gap_s``.
- CAN and I2C replay devices: :mod:`u2sa_hw.hil.replay_buses`; GPIO and PWM: :mod:`u2sa_hw.hil.replay_gpio`.

Every device has ``config_changes()`` (the config fields that point its driver at it),
``start()``/``stop()``, ``ready(pid, health)`` (the driver has opened its side), ``feed(record)``,
``pending()`` (input the driver has not taken yet: the pacing of ``--fast``) and
``report()`` (counts and divergences for the summary): :class:`ReplayDevice`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

from u2sa_hw.ports.address import DeviceAddress
from u2sa_hw.ports.serial.replay import ReplaySerialDevice


class ReplayDevice(Protocol):
    """What the player and the orchestration need from a replay device."""

    name: str
    kind: str

    def mock_address(self, real: DeviceAddress | None) -> str:
        """The ``mock+`` address the driver opens instead of the recorded *real* one (same kind)."""

    def config_changes(self) -> dict[str, Any]:
        """Config fields the replay needs changed besides the address (e.g. a faster rate)."""

    def start(self) -> None:
        """Open the device (before the driver starts)."""

    def stop(self) -> None:
        """Close it."""

    def ready(self, pid: int | None, health: dict[str, str]) -> bool:
        """True once the driver (process *pid*, whose latest health details are *health*) has opened its side."""

    def feed(self, record: Any) -> None:
        """Play one recorded record (RX) or note one the driver should send (TX)."""

    def pending(self) -> int:
        """Input fed but not yet taken by the driver."""

    def report(self) -> dict[str, Any]:
        """Counts and divergences."""


def replay_options_of(dev: Any, service: Any) -> dict[str, Any]:
    """What the driver of *service* (a ServicePlan) declares a replay of *dev* needs, from the recorded config
    and the overrides (``replay_options``, :mod:`u2sa_hw.ports.declared`); ReplayError when its kind cannot
    be loaded."""
    from u2sa_hw.hil.replay_plan import ReplayError
    from u2sa_hw.ports.declared import declared_class, replay_options

    try:
        cls = declared_class(service.kind)
    except (LookupError, ImportError) as exc:   # reported, as typed_overrides does
        raise ReplayError(f"service '{service.name}': cannot load kind '{service.kind}' ({exc})") from None
    return replay_options(cls, dev.name, {**service.config, **service.overrides})


def make_serial_device(dev: Any, run_dir: Path, *, service: Any, fast: bool,
                       rigs: dict[str, Any]) -> ReplaySerialDevice:
    """The serial kind's replay device (``PORT_KINDS["serial"].replay``): a stamped pty at
    ``<run>/dev/<device>``, its bursts cut at the driver's declared ``burst_gap_s``."""
    gap = replay_options_of(dev, service).get("burst_gap_s")
    return ReplaySerialDevice(name=dev.name, link_path=run_dir / "dev" / dev.name, stamped=True,
                              **({"burst_gap_s": float(gap)} if isinstance(gap, (int, float)) else {}))
