"""The CAN kind's probe (``u2sa check --probe``): the interface's state, bitrate and error counters, and the
node ids heard in the window.

SocketCAN's state comes from ``/sys/class/net`` and ``ip -details -statistics link``; a
python-can ``udp_multicast``/``virtual`` bus is said to be simulated. The probe only listens.
Which frames name a node is the driver's protocol's to say: the protocol its driver declares
(``probe_expectation``) names a module in :data:`u2sa_hw.registry.CAN_PROTOCOLS`, whose
``probe_node(frame)`` and ``PROBE_SEEN`` are used here, so a new CAN motor family adds no branch.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping

if TYPE_CHECKING:
    from u2sa_hw.check.targets import Target
    from u2sa_hw.ports.address import DeviceAddress

PROBE = "can"             # the probe's name (a target's ``port``)


def target_params(address: DeviceAddress, expect: Mapping[str, Any]) -> dict[str, Any]:
    """The interface, channel and bus options of a CAN *address*, and what the driver expects (``protocol``,
    ``nodes``)."""
    return {"interface": address.can_interface, "channel": address.can_channel, "bus_options": address.bus_options,
            **expect}


SIMULATED_CAN = ("udp_multicast", "virtual")


def socketcan_state(interface: str, *, run: Callable[..., Any] | None = None) -> tuple[bool, str]:
    """``(up, "state ERROR-ACTIVE, 500000 bit/s, tx/rx errors 0/0, bus-off 0")`` of a SocketCAN interface."""
    import re
    import subprocess

    base = Path("/sys/class/net") / interface
    if not base.exists():
        return False, (f"no interface {interface} (modprobe can can_raw and the adapter's driver; "
                       f"ip link show lists interfaces)")
    operstate = (base / "operstate").read_text().strip() if (base / "operstate").exists() else "?"
    runner = run or subprocess.run
    try:
        shown = runner(["ip", "-details", "-statistics", "link", "show", interface], capture_output=True,
                       text=True, timeout=5).stdout
    except (OSError, subprocess.SubprocessError) as exc:
        return operstate == "up", f"link {operstate} (ip failed: {exc})"
    parts = [f"link {operstate}"]
    state = re.search(r"can (?:<[^>]*> )?state ([A-Z-]+)", shown)
    if state:
        parts.append(f"state {state.group(1)}")
    bitrate = re.search(r"bitrate (\d+)", shown)
    parts.append(f"{bitrate.group(1)} bit/s" if bitrate else "no bitrate set")
    counters = re.search(r"berr-counter tx (\d+) rx (\d+)", shown)
    if counters:
        parts.append(f"tx/rx error counters {counters.group(1)}/{counters.group(2)}")
    restarts = re.search(r"re-started\s+bus-errors\s+arbit-lost\s+error-warn\s+error-pass\s+bus-off"
                         + r"\s+(\d+)" * 6, shown)
    if restarts:
        parts.append(f"bus errors {restarts.group(2)}, bus-off {restarts.group(6)}")
    healthy = operstate in ("up", "unknown") and (state is None or state.group(1) == "ERROR-ACTIVE")
    return healthy, ", ".join(parts)


def heard_nodes(frames: list[Any], protocol: str) -> list[int]:
    """The node ids in *frames* that *protocol*'s module recognises (its ``probe_node``: an ODrive's
    heartbeats, a VESC's status frames); none for a protocol the table does not name."""
    recognise = _recogniser(protocol)
    if recognise is None:
        return []
    return sorted({node for node in map(recognise, frames) if node is not None})


def seen_as(protocol: str) -> str:
    """What the frames *protocol*'s probe recognises are called (``ODrive heartbeats``); ``frames`` else."""
    from u2sa_hw.registry import CAN_PROTOCOLS, can_protocol

    return str(can_protocol(protocol).PROBE_SEEN) if protocol in CAN_PROTOCOLS else "frames"


def _recogniser(protocol: str) -> Callable[[Any], int | None] | None:
    """*protocol*'s ``probe_node`` from the CAN protocol table (:data:`u2sa_hw.registry.CAN_PROTOCOLS`)."""
    from u2sa_hw.registry import CAN_PROTOCOLS, can_protocol

    return can_protocol(protocol).probe_node if protocol in CAN_PROTOCOLS else None


def probe(target: Target, seconds: float) -> tuple[bool, str, dict[str, Any]]:
    """The bus's state (SocketCAN) and the node ids heard in *seconds*; a configured node not heard fails."""
    from u2sa_hw.ports.can.port import open_can

    interface, channel = str(target.params["interface"]), str(target.params["channel"])
    if interface in SIMULATED_CAN:
        ok, state = True, f"simulated bus (python-can {interface}): no bus state or error counters"
    elif interface == "socketcan":
        ok, state = socketcan_state(channel)
    else:
        ok, state = True, f"python-can {interface}: state not readable"
    options = dict(target.params.get("bus_options", {}))
    port = open_can(device=target.name, interface=interface, channel=channel, **options)
    frames = []
    try:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            msg = port.recv(timeout=min(0.2, max(0.0, end - time.monotonic())))
            if msg is not None:
                frames.append(msg)
    finally:
        port.close()
    protocol = str(target.params.get("protocol", ""))
    nodes = heard_nodes(frames, protocol)
    wanted = [int(n) for n in target.params.get("nodes", [])]
    missing = [n for n in wanted if n not in nodes]
    what = seen_as(protocol)
    text = (f"{state}; {len(frames)} frames in {seconds:g} s, {what} from node(s) "
            f"{', '.join(map(str, nodes)) or 'none'}")
    if missing:
        text += f"; configured node(s) {', '.join(map(str, missing))} not heard (power, wiring, node id)"
    return ok and not missing, text, {"nodes": nodes, "frames": len(frames)}
