"""Mock CAN motor controllers in a process of their own, scriptable from the test over a pipe.

``python tests/can_mock_harness.py '<json spec>'`` runs one SimVehicle and the ODrive or VESC
nodes the spec names on a udp_multicast bus, prints one ``{"ready": ...}`` line, then answers
JSON requests, one per stdin line, with one JSON line on stdout:

    {"op": "truth"}                                   -> the vehicle's VehicleTruth as a dict
    {"op": "get", "node": "left", "attr": "axis_state"}  -> {"value": ...}
    {"op": "call", "node": "left", "method": "stop_answering", "args": [true]} -> {"value": ...}
    {"op": "received", "node": "left"}                -> [[arbitration_id, "data hex"], ...]
        (the frames the node accepted, oldest first)

The driver under test runs as a real ``u2sa service`` process and meets these nodes only on
the bus, exactly as it would meet hardware. :class:`MockCanProcess` is the test's side.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import threading
from enum import Enum
from pathlib import Path
from typing import Any

GROUP = "239.74.163.2"  # python-can's default IPv4 group for udp_multicast


def _plain(value: Any) -> Any:
    if isinstance(value, Enum):
        return value.value
    if isinstance(value, (int, float, str, bool)) or value is None:
        return value
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return repr(value)


def serve(spec: dict[str, Any]) -> None:
    """Run the vehicle and nodes of *spec* and answer requests until stdin closes."""
    from u2sa_hw.mocks.odrive_node import OdriveCanNode
    from u2sa_hw.mocks.vehicle_sim import SimVehicle
    from u2sa_hw.mocks.vesc_node import VescCanNode

    vehicle = SimVehicle(origin_lat=0.0, origin_lon=0.0, **spec.get("vehicle", {}))
    cls = {"odrive": OdriveCanNode, "vesc": VescCanNode}[spec["kind"]]
    bus = {"interface": "udp_multicast", "channel": GROUP, "bus_options": {"port": spec["port"]}}
    nodes = {n["side"]: cls(vehicle, **bus, **n) for n in spec["nodes"]}
    vehicle.start()
    for node in nodes.values():
        node.start()
    print(json.dumps({"ready": sorted(nodes)}), flush=True)
    try:
        for line in sys.stdin:
            request = json.loads(line)
            try:
                reply = {"value": _answer(request, vehicle, nodes)}
            except Exception as exc:  # noqa: BLE001 - the test sees the error instead of a hang
                reply = {"error": f"{type(exc).__name__}: {exc}"}
            print(json.dumps(reply), flush=True)
    finally:
        for node in nodes.values():
            node.stop()
        vehicle.stop()


def _answer(request: dict[str, Any], vehicle: Any, nodes: dict[str, Any]) -> Any:
    op = request["op"]
    if op == "truth":
        return dataclasses.asdict(vehicle.snapshot())
    node = nodes[request["node"]]
    if op == "received":
        return [[r.message.arbitration_id, r.message.data.hex()] for r in node.history if r.direction == "rx"]
    if op == "get":
        return _plain(getattr(node, request["attr"]))
    if op == "call":
        return _plain(getattr(node, request["method"])(*request.get("args", []), **request.get("kwargs", {})))
    raise ValueError(f"unknown op {op!r}")


class MockCanProcess:
    """The test's handle on a harness process: start, request, stop."""

    def __init__(self, spec: dict[str, Any], *, repo: Path, log: Path) -> None:
        self._log = open(log, "wb")
        self.proc = subprocess.Popen([sys.executable, str(Path(__file__)), json.dumps(spec)], cwd=repo,
                                     env=dict(os.environ, PYTHONPATH=str(repo)),
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._log, text=True)
        self._lock = threading.Lock()
        ready = self.proc.stdout.readline() if self.proc.stdout else ""
        if not ready.startswith('{"ready"'):
            self.stop()
            raise RuntimeError(f"mock CAN harness did not start: {ready!r}; see {log}")

    def request(self, **request: Any) -> Any:
        """Send one request and return its value (RuntimeError if the harness reports one)."""
        assert self.proc.stdin is not None and self.proc.stdout is not None
        with self._lock:
            self.proc.stdin.write(json.dumps(request) + "\n")
            self.proc.stdin.flush()
            reply = json.loads(self.proc.stdout.readline())
        if "error" in reply:
            raise RuntimeError(reply["error"])
        return reply["value"]

    def truth(self) -> dict[str, Any]:
        """The vehicle's state now."""
        return self.request(op="truth")

    def get(self, node: str, attr: str) -> Any:
        """An attribute of the node on *node*'s side."""
        return self.request(op="get", node=node, attr=attr)

    def call(self, node: str, method: str, *args: Any, **kwargs: Any) -> Any:
        """Call a method (a fault, usually) of the node on *node*'s side."""
        return self.request(op="call", node=node, method=method, args=list(args), kwargs=kwargs)

    def received(self, node: str) -> list[tuple[int, bytes]]:
        """The frames the node on *node*'s side accepted so far: (arbitration id, data), oldest first."""
        return [(can_id, bytes.fromhex(data)) for can_id, data in self.request(op="received", node=node)]

    def stop(self) -> None:
        """Close stdin (the harness stops its nodes) and reap the process."""
        if self.proc.stdin is not None:
            try:
                self.proc.stdin.close()
            except OSError:
                pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self._log.close()


class Commander:
    """A stand-in control system: Percentage Commands every *period* while set, and failsafes."""

    def __init__(self, bus: Any, *, period: float = 0.1) -> None:
        self.bus = bus
        self.period = period
        self._targets: dict[str, float] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="commander", daemon=True)
        self._thread.start()

    def send(self, actuator: str, percent: float) -> None:
        """Publish one Percentage Command now."""
        from u2sa_hw import channels as ch
        from u2sa_hw import lcmtypes as t

        msg = t.PercentageCommand()
        msg.base.actuator_name = actuator
        msg.percentage = percent
        self.bus.publish(ch.ACTUATOR_CMD, msg)

    def hold(self, **percent: float) -> None:
        """Keep commanding these actuators (name=percent) every period, starting now."""
        with self._lock:
            self._targets.update(percent)
        for name, value in percent.items():
            self.send(name, value)

    def release(self) -> None:
        """Stop commanding anything (the driver's command timeout should then act)."""
        with self._lock:
            self._targets.clear()

    def failsafe(self, active: bool, reason: str = "test") -> None:
        """Publish a FAILSAFE message."""
        from u2sa_hw import channels as ch
        from u2sa_hw import lcmtypes as t

        msg = t.Failsafe()
        msg.active, msg.reason, msg.service = active, reason, "test"
        self.bus.publish(ch.FAILSAFE, msg)

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            with self._lock:
                targets = dict(self._targets)
            for name, value in targets.items():
                self.send(name, value)

    def close(self) -> None:
        """Stop the thread."""
        self._stop.set()
        self._thread.join(timeout=2)


if __name__ == "__main__":
    serve(json.loads(sys.argv[1]))


def stop_driver(driver: Any, bus: Any, how: str, *, name: str = "motors") -> None:
    """Stop the driver process over the bus (``how == "u2sa stop"``) or with SIGTERM; it must exit 0."""
    if how == "u2sa stop":
        bus.stop(name=name)
    else:
        driver.terminate()
    assert driver.wait(timeout=15) == 0
