"""``u2sa check --probe``: open each device of a profile and look at it, one line per device.

Serial: :mod:`u2sa_hw.check.serial_probe` (line rate, protocol, good checksums, the baud
that works). I2C: the chip's identity register against what the driver expects
(:mod:`u2sa_hw.check.chip_ids`). CAN: the interface's state, bitrate and error counters
(socketcan: ``/sys/class/net`` and ``ip -details -statistics link``; a python-can
``udp_multicast``/``virtual`` bus is said to be simulated) and the node ids heard in the
window. GPIO: the lines exist and no one holds them. PWM: the channel exists. A device whose
address kind has no probe (:data:`PROBES`, chosen through :data:`u2sa_hw.check.targets.TARGETS`)
gets a ``probe skip`` line saying so: never probed without a word, and not a failure.

Nothing is written to a device: a probe only reads (an I2C identity register, the GPIO
lines' info) and listens. A device held by a running service is reported busy; stop the
service (or probe before starting it) to look at it.
"""

from __future__ import annotations

import errno
import json
import os
import socket
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

from u2sa_hw.check.chip_ids import expected_identity, read_identity
from u2sa_hw.check.targets import Target, profile_targets


@dataclass(frozen=True)
class ProbeResult:
    """What a probe of one device found: ``ok`` False when it cannot work as configured."""

    device: str
    port: str
    address: str
    ok: bool
    text: str
    details: Mapping[str, Any] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()      # it works, but not as well as it could (an uncalibrated sensor)
    probed: bool = True                 # False: no probe for the device's kind (ok, since nothing was found wrong)

    def __str__(self) -> str:
        status = "ok  " if self.ok else "FAIL"
        line = f"probe {status if self.probed else 'skip'} {self.device}: {self.port} {self.address}: {self.text}"
        return "\n".join([line, *(f"probe warn {self.device}: {w}" for w in self.warnings)])

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        data = asdict(self)
        data["details"] = dict(self.details)
        return data


def probe_profile(profile: Any, *, seconds: float = 3.0) -> list[ProbeResult]:
    """Probe every device of every enabled service of *profile*, all at once (each listens *seconds*).

    The devices are independent, so they are probed on threads: the wall time is about one
    window, not one per device. The results keep the profile's device order.
    """
    from concurrent.futures import ThreadPoolExecutor

    targets = profile_targets(profile)
    if not targets:
        return []
    with ThreadPoolExecutor(max_workers=len(targets), thread_name_prefix="probe") as pool:
        results = list(pool.map(lambda target: probe_target(target, seconds=seconds), targets))
    from u2sa_hw.check.probe_calibration import with_calibration_warnings

    return [with_calibration_warnings(profile, target, result) for target, result in zip(targets, results)]


def probe_target(target: Target, *, seconds: float) -> ProbeResult:
    """One device: the probe of its port kind (none: a "no probe for kind" line); a port error becomes a failed
    line with its fix."""
    from u2sa_hw.ports.errors import PortError

    probe = PROBES.get(target.port)
    if probe is None:
        kind = target.kind or target.port
        return ProbeResult(target.name, kind, target.address, True,
                           f"no probe for kind {kind}: not looked at (check it by hand; a probe for the kind goes in "
                           "u2sa_hw/check/probe.py, see docs/ports.md, 'A new port kind')", probed=False)
    try:
        ok, text, details = probe(target, seconds)
    except PortError as exc:
        ok, text, details = False, str(exc).replace(f"{target.name} ({target.address}): ", ""), {}
    except OSError as exc:
        ok, text, details = False, f"{exc.strerror or exc}", {}
    return ProbeResult(target.name, target.port, target.address, ok, text, details)


# ---- serial ---------------------------------------------------------------------------------
def _probe_serial(target: Target, seconds: float) -> tuple[bool, str, dict[str, Any]]:
    from u2sa_hw.check.serial_probe import probe_serial_port
    from u2sa_hw.ports import open_serial

    baud = int(target.params.get("baud", 9600))
    path = str(target.params["path"])
    ok, text = probe_serial_port(lambda rate: open_serial(path, device=target.name, baudrate=rate, timeout=0.1),
                                 baud=baud, seconds=seconds)
    expect = target.params.get("protocol")
    if ok and expect and expect.upper() not in text:
        return False, f"{text}; the driver expects {expect} (from its service's config)", {}
    return ok, text, {}


# ---- I2C ------------------------------------------------------------------------------------
def _probe_i2c(target: Target, seconds: float) -> tuple[bool, str, dict[str, Any]]:
    from u2sa_hw.ports.i2c.port import open_i2c

    chip = target.params["chip"]
    address = int(target.params["address"])
    expected = expected_identity(chip, target.params.get("variant", "auto"))
    port = open_i2c(device=target.name, bus=target.params["bus"], address=address)
    try:
        ok, text = read_identity(port, expected)
        extra = expected.companion(port, bus=target.params["bus"], device=target.name) if ok else ""
    finally:
        port.close()
    return ok, text + extra, {"chip": chip, "address": address}


# ---- CAN ------------------------------------------------------------------------------------
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
    """The node ids in *frames*: ODrive heartbeats (id >> 5, cmd 0x01), VESC status frames (id & 0xFF)."""
    from u2sa_hw.protocols import odrive_cansimple as od
    from u2sa_hw.protocols import vesc_can as vesc

    nodes: set[int] = set()
    for msg in frames:
        if protocol == "odrive" and not msg.is_extended_id and msg.arbitration_id <= 0x7FF:
            node, cmd = od.split_arbitration_id(msg.arbitration_id)
            if cmd == 0x01:
                nodes.add(node)
        elif protocol == "vesc" and msg.is_extended_id and msg.arbitration_id <= 0xFFFF:
            packet, node = vesc.split_ext_id(msg.arbitration_id)
            if packet in {int(p) for p in vesc.STATUS_PACKETS}:
                nodes.add(node)
    return sorted(nodes)


def _probe_can(target: Target, seconds: float) -> tuple[bool, str, dict[str, Any]]:
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
    what = {"odrive": "ODrive heartbeats", "vesc": "VESC status frames"}.get(protocol, "frames")
    text = (f"{state}; {len(frames)} frames in {seconds:g} s, {what} from node(s) "
            f"{', '.join(map(str, nodes)) or 'none'}")
    if missing:
        text += f"; configured node(s) {', '.join(map(str, missing))} not heard (power, wiring, node id)"
    return ok and not missing, text, {"nodes": nodes, "frames": len(frames)}


# ---- GPIO -----------------------------------------------------------------------------------
def _mock_gpio_info(path: str) -> dict[str, Any]:
    from u2sa_hw.ports.gpio.wire import MOCK_JSON, encode_mock_json, MockFrameReader

    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(3.0)
        sock.connect(path)
        sock.sendall(encode_mock_json({"op": "info", "id": 1}))
        reader = MockFrameReader()
        while True:
            data = sock.recv(65536)
            if not data:
                raise ConnectionError("the mock chip closed the connection")
            for kind, payload in reader.feed(data):
                if kind == MOCK_JSON:
                    return json.loads(payload)


def _gpio_info(chip: str) -> tuple[int, dict[int, str]]:
    """``(number of lines, {line: consumer})`` of the lines in use on *chip*."""
    if chip.startswith("mock:"):
        info = _mock_gpio_info(chip[len("mock:"):])
        used = {int(n): str(v.get("consumer", "?")) for n, v in info.get("lines", {}).items()}
        return int(info["num_lines"]), used
    path = chip if chip.startswith("/") else f"/dev/{chip}"
    if not Path(path).exists():   # said before gpiod is needed: the address is what is wrong
        raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), path)
    import gpiod   # libgpiod v2, only on a vehicle

    with gpiod.Chip(path) as handle:
        count = handle.get_info().num_lines
        used = {}
        for line in range(count):
            info = handle.get_line_info(line)
            if info.used:
                used[line] = info.consumer or "?"
        return count, used


def _probe_gpio(target: Target, seconds: float) -> tuple[bool, str, dict[str, Any]]:
    chip = str(target.params["chip"])
    lines = [int(n) for n in target.params.get("lines", [])]
    try:
        count, used = _gpio_info(chip)
    except ImportError:
        return False, "python gpiod (libgpiod v2) is not installed: pip install gpiod", {}
    except OSError as exc:
        return False, _gpio_chip_problem(target, chip, exc), {}
    missing = [n for n in lines if not 0 <= n < count]
    busy = {n: used[n] for n in lines if n in used}
    parts = [f"{count} lines"]
    if missing:
        parts.append(f"line(s) {', '.join(map(str, missing))} do not exist (0..{count - 1})")
    if busy:
        parts.append("held: " + ", ".join(f"{n} by '{c}'" for n, c in busy.items()) + " (stop that service first)")
    if not missing and not busy:
        parts.append(f"line(s) {', '.join(map(str, lines)) or 'none'} exist and are free")
    return not missing and not busy, "; ".join(parts), {"lines": lines, "busy": busy}


def _gpio_chip_problem(target: Target, chip: str, exc: OSError) -> str:
    """Why the chip of *target* cannot be looked at, with the fix (not a bare "No such file or directory")."""
    reason = exc.strerror or str(exc)
    lines = ",".join(str(n) for n in target.params.get("lines", [])) or "LINES"
    if chip.startswith("mock:"):
        return (f"device '{target.name}': no mock GPIO chip at {chip[len('mock:'):]} ({reason}); fix: start the "
                "mocks first (u2sa mock --vehicle ...) and probe the profile it writes, or correct the socket path")
    path = chip if chip.startswith("/") else f"/dev/{chip}"
    if isinstance(exc, PermissionError):
        return (f"device '{target.name}': cannot open GPIO chip {path} ({reason}); fix: run as a member of the gpio "
                "group (u2sa install adds the service user to it) or as root")
    return (f"device '{target.name}': no GPIO chip {path} ({reason}); fix: list the chips with gpiodetect and write "
            f"the right one in [devices.{target.name}] address, e.g. gpio://gpiochip0/{lines} (docs/ports.md), "
            "or enable the GPIO controller (its device-tree overlay)")


# ---- PWM ------------------------------------------------------------------------------------
def _probe_pwm(target: Target, seconds: float) -> tuple[bool, str, dict[str, Any]]:
    chip = Path(str(target.params["chip"]))
    channel = int(target.params["channel"])
    if not chip.is_dir():
        return False, f"no PWM chip at {chip} (enable the PWM overlay, e.g. dtoverlay=pwm-2chan)", {}
    try:
        npwm = int((chip / "npwm").read_text().strip())
    except (OSError, ValueError):
        return False, f"{chip}/npwm cannot be read", {}
    if not 0 <= channel < npwm:
        return False, f"channel {channel} does not exist ({chip.name} has {npwm}: 0..{npwm - 1})", {}
    exported = (chip / f"pwm{channel}").is_dir()
    return True, f"channel {channel} of {npwm} exists" + (" (exported: in use)" if exported else ""), {}


PROBES: dict[str, Callable[[Target, float], tuple[bool, str, dict[str, Any]]]] = {
    "serial": _probe_serial, "i2c": _probe_i2c, "can": _probe_can, "gpio": _probe_gpio, "pwm": _probe_pwm,
}
