"""The live Foxglove bridge (``u2sa foxglove``) with a real WebSocket client speaking the SDK's protocol.

The client (the ``websockets`` package) connects with the subprotocol the foxglove-sdk
server speaks (``foxglove.sdk.v1``: serverInfo, advertise, subscribe, binary messageData,
getParameters/setParameters -> parameterValues); LCM publishers are real (a BusClient on
the test's signed bus) and so is the service whose config is read and changed.
"""

from __future__ import annotations

import asyncio
import json
import re
import struct
import subprocess
from pathlib import Path
from typing import Any

import jsonschema
import pytest
from conftest import U2SA, ServiceProcesses, wait_until

from u2sa_hw import lcmtypes as t

websockets = pytest.importorskip("websockets")
InvalidStatus = pytest.importorskip("websockets.exceptions").InvalidStatus
pytest.importorskip("foxglove")

SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 0x01
PROFILE = '[vehicle]\nname = "rover"\nlog_dir = ".u2sa/logs"\norigin = { lat = 29.19, lon = -81.05, alt = 10.0 }\n'


def start_bridge(services: ServiceProcesses, *args: str) -> tuple[subprocess.Popen, Path]:
    """``u2sa foxglove`` in the test's directory; returns the process and its stderr file."""
    (services.workdir / "vehicle.toml").write_text(PROFILE)
    err = services.workdir / "foxglove.stderr"
    proc = subprocess.Popen([*U2SA, "foxglove", "--vehicle", "vehicle.toml", "--port", "0", *args],
                            cwd=services.workdir, env=services.env(), stdout=subprocess.DEVNULL,
                            stderr=open(err, "wb"))
    services.procs.append(proc)
    return proc, err


def bridge_port(proc: subprocess.Popen, err: Path) -> int:
    def port() -> int | None:
        assert proc.poll() is None, err.read_text()
        m = re.search(r"Foxglove: open wss?://[^:]+:(\d+)", err.read_text())
        return int(m.group(1)) if m else None

    return int(wait_until(port, timeout=30, interval=0.1, message="the bridge to listen"))


class Client:
    """A Foxglove WebSocket client: keeps the advertised channels, collects messageData per subscription."""

    def __init__(self, ws: Any) -> None:
        self.ws = ws
        self.channels: dict[str, dict[str, Any]] = {}
        self.data: dict[int, list[tuple[int, dict[str, Any]]]] = {}
        self.replies: list[dict[str, Any]] = []
        self.status: list[dict[str, Any]] = []

    async def pump(self, until: Any, *, timeout: float, tick: Any = None) -> None:
        """Read frames until ``until()`` holds, calling ``tick()`` (a publisher) every 50 ms meanwhile."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while not until():
            if loop.time() > deadline:
                pytest.fail(f"timed out; advertised {sorted(self.channels)}, replies {self.replies}")
            if tick is not None:
                tick()
            try:
                frame = await asyncio.wait_for(self.ws.recv(), 0.05)
            except asyncio.TimeoutError:
                continue
            if isinstance(frame, bytes):
                op, sub_id, ts = struct.unpack_from("<BIQ", frame)
                assert op == MESSAGE_DATA
                self.data.setdefault(sub_id, []).append((ts, json.loads(frame[13:])))
                continue
            msg = json.loads(frame)
            if msg["op"] == "advertise":
                self.channels.update({c["topic"]: c for c in msg["channels"]})
            elif msg["op"] == "status":
                self.status.append(msg)
            else:
                self.replies.append(msg)

    async def subscribe(self, topics: dict[int, str]) -> None:
        subs = [{"id": sid, "channelId": self.channels[topic]["id"]} for sid, topic in topics.items()]
        await self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def validated(self, sub_id: int, topic: str) -> list[dict[str, Any]]:
        """Payloads of a subscription, each checked against the schema its channel advertised."""
        schema = json.loads(self.channels[topic]["schema"])
        payloads = [p for _ts, p in self.data.get(sub_id, [])]
        for p in payloads:
            jsonschema.validate(p, schema)
        return payloads


def estimate(i: int) -> t.StateInformation:
    s = t.StateInformation().set(x=10.0 + i * 0.01, y=-5.0, psi=0.5, x_sigma=0.4, y_sigma=0.4)
    s.sensor_name, s.reference_frame = "state_estimator", "NED"
    return s


@pytest.mark.timeout(120)
def test_live_topics_parameters_and_logs(services: ServiceProcesses, bus: Any) -> None:
    proc, err = start_bridge(services, "--allow-parameter-writes")
    port = bridge_port(proc, err)
    services.start("world", "--kind", "world_modeler")
    wait_until(lambda: any(r.name == "world" for r in bus.discover(timeout=0.3)), timeout=30,
               message="the world modeler")
    counter = [0]

    def publish() -> None:
        counter[0] += 1
        bus.publish("STATE_ESTIMATE", estimate(counter[0]))
        edge, write = t.RawGpioEdge(), t.RawGpioWrite()
        edge.device, edge.line, edge.edge = "rc", 3, 1
        write.device, write.line, write.value = "rc", 7, 1
        bus.publish("RAW.rc", edge)
        bus.publish("RAW.rc", write)

    async def session() -> Client:
        async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL]) as ws:
            c = Client(ws)
            info = json.loads(await ws.recv())
            assert info["op"] == "serverInfo" and "parameters" in info["capabilities"]
            wanted = {"STATE_ESTIMATE", "/location/STATE_ESTIMATE", "/tf", "RAW.rc/RawGpioEdge",
                      "RAW.rc/RawGpioWrite", "/log"}
            await c.pump(lambda: wanted <= set(c.channels), timeout=30, tick=publish)
            assert c.channels["/location/STATE_ESTIMATE"]["schemaName"] == "foxglove.LocationFix"
            assert c.channels["RAW.rc/RawGpioWrite"]["schemaName"] == "u2sa.RawGpioWrite"
            await c.subscribe({1: "/location/STATE_ESTIMATE", 2: "/tf", 3: "RAW.rc/RawGpioEdge",
                               4: "RAW.rc/RawGpioWrite", 5: "/log"})
            await c.pump(lambda: all(len(c.data.get(i, [])) >= 3 for i in (1, 2, 3, 4)), timeout=30, tick=publish)
            await ws.send(json.dumps({"op": "getParameters", "parameterNames": [], "id": "all"}))
            await c.pump(lambda: any(r.get("id") == "all" for r in c.replies), timeout=30)
            await ws.send(json.dumps({"op": "setParameters", "id": "set",
                                      "parameters": [{"name": "world.log_level", "value": "debug"}]}))
            await c.pump(lambda: any(r.get("id") == "set" for r in c.replies), timeout=30)
            # the service logs the change into its log file; the bridge tails it onto /log
            await c.pump(lambda: any("log level is now debug" in p["message"] for _ts, p in c.data.get(5, [])),
                         timeout=30)
            return c

    c = asyncio.run(session())
    fixes = c.validated(1, "/location/STATE_ESTIMATE")
    assert 29.19 < fixes[-1]["latitude"] < 29.2 and fixes[-1]["position_covariance_type"] == 2
    tf = c.validated(2, "/tf")[-1]
    assert (tf["parent_frame_id"], tf["child_frame_id"]) == ("world", "base_link")
    assert tf["translation"]["x"] == pytest.approx(-5.0) and tf["translation"]["y"] > 10.0   # east, north
    assert {p["_type"] for p in c.validated(3, "RAW.rc/RawGpioEdge")} == {"RawGpioEdge"}
    assert {p["_type"] for p in c.validated(4, "RAW.rc/RawGpioWrite")} == {"RawGpioWrite"}
    logs = c.validated(5, "/log")
    assert any(p["name"] == "world" and p["level"] == 2 for p in logs)
    values = {p["name"]: p["value"] for r in c.replies if r.get("id") == "all" for p in r["parameters"]}
    assert values["world.log_level"] == "" and "foxglove.queue_size" in values
    changed = {p["name"]: p["value"] for r in c.replies if r.get("id") == "set" for p in r["parameters"]}
    assert changed == {"world.log_level": "debug"}
    assert services.cli("param", "get", "world", "log_level").stdout.strip() == '"debug"'


@pytest.mark.timeout(60)
def test_parameter_writes_are_refused_unless_allowed(services: ServiceProcesses, bus: Any) -> None:
    proc, err = start_bridge(services)
    port = bridge_port(proc, err)

    async def session() -> Client:
        async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL]) as ws:
            c = Client(ws)
            await ws.send(json.dumps({"op": "setParameters", "id": "set",
                                      "parameters": [{"name": "foxglove.queue_size", "value": 7}]}))
            await c.pump(lambda: any(r.get("id") == "set" for r in c.replies) and c.status, timeout=30)
            return c

    c = asyncio.run(session())
    (reply,) = [r for r in c.replies if r.get("id") == "set"]
    assert reply["parameters"] == [{"name": "foxglove.queue_size", "value": 5000}]
    assert "parameter writes are off" in c.status[0]["message"]


@pytest.mark.timeout(60)
def test_network_exposure_needs_a_token_and_the_gate_checks_it(services: ServiceProcesses, bus: Any) -> None:
    refused = subprocess.run([*U2SA, "foxglove", "--host", "0.0.0.0", "--port", "0"], cwd=services.workdir,
                             env=services.env(), capture_output=True, text=True, timeout=30)
    assert refused.returncode != 0 and "token_file" in refused.stderr
    token = "s3cret-token-of-the-test-0123456789"
    (services.workdir / "token").write_text(token + "\n")
    proc, err = start_bridge(services, "--host", "0.0.0.0", "--token-file", "token")
    port = bridge_port(proc, err)

    async def connect(query: str) -> str:
        async with websockets.connect(f"ws://127.0.0.1:{port}/{query}", subprotocols=[SUBPROTOCOL]) as ws:
            return json.loads(await ws.recv())["op"]

    for wrong in ("", "?token=guess"):
        with pytest.raises(InvalidStatus) as exc:
            asyncio.run(connect(wrong))
        assert exc.value.response.status_code == 401
    assert asyncio.run(connect(f"?token={token}")) == "serverInfo"


@pytest.mark.timeout(60)
def test_a_full_queue_drops_and_counts_instead_of_slowing_the_bus(services: ServiceProcesses, bus: Any) -> None:
    proc, err = start_bridge(services, "--queue-size", "1")
    bridge_port(proc, err)
    seen: dict[str, Any] = {}
    bus.transport.subscribe("U2SA_HEALTH", t.Health, lambda _c, m: seen.update(
        {"status": m.status, **{kv.key: kv.value for kv in m.details}}) if m.name == "foxglove" else None)
    edge = t.RawGpioEdge()
    edge.device, edge.line = "rc", 3
    burst = [0]

    def dropped() -> bool:
        if burst[0] < 10:   # a few bursts of back-to-back packets: far more than one queue slot can take
            burst[0] += 1
            for _ in range(500):
                bus.publish("RAW.rc", edge)
        return int(seen.get("dropped", 0)) > 0 and seen.get("status") == "degraded"

    wait_until(dropped, timeout=30, interval=0.3, message="the bridge's health to count drops")
    assert int(seen["received"]) >= int(seen["dropped"]) > 0
    assert proc.poll() is None
