"""The live Foxglove bridge (``u2sa foxglove``) with a real WebSocket client speaking the SDK's protocol.

The client (the ``websockets`` package) connects with the subprotocol the foxglove-sdk
server speaks (``foxglove.sdk.v1``: serverInfo, advertise, subscribe, binary messageData,
getParameters/setParameters -> parameterValues); LCM publishers are real (a BusClient on
the test's signed bus) and so is the service whose config is read and changed. The bridge's
own reach (host, token, TLS, writes) is not changeable remotely, and a listener beyond
loopback without a good token is refused by ``u2sa check`` and at start in one line.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import struct
import subprocess
from pathlib import Path
from typing import Any, AsyncIterator

import jsonschema
import pytest
from conftest import U2SA, ServiceProcesses, wait_until

from u2sa_hw import lcmtypes as t
from u2sa_hw.foxglove.mapping import HEALTH, SCENE_WORLD, FoxgloveMapper
from u2sa_hw.geo import ned_to_geodetic
from u2sa_hw.profile.vehicle import Origin

websockets = pytest.importorskip("websockets")
InvalidStatus = pytest.importorskip("websockets.exceptions").InvalidStatus
pytest.importorskip("foxglove")

SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 0x01
PROFILE = '[vehicle]\nname = "rover"\nlog_dir = ".u2sa/logs"\norigin = { lat = 29.19, lon = -81.05, alt = 10.0 }\n'
NO_ORIGIN_PROFILE = '[vehicle]\nname = "rover"\nlog_dir = ".u2sa/logs"\n'


def start_bridge(services: ServiceProcesses, *args: str, profile: str = PROFILE) -> tuple[subprocess.Popen, Path]:
    """``u2sa foxglove`` in the test's directory; returns the process and its stderr file."""
    (services.workdir / "vehicle.toml").write_text(profile)
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
        next_tick = loop.time()
        while not until():
            if loop.time() > deadline:
                got = {sub_id: len(items) for sub_id, items in sorted(self.data.items())}
                pytest.fail(f"timed out after {timeout:g} s; advertised {sorted(self.channels)}, replies "
                            f"{self.replies}, status {self.status}, messages per subscription {got}")
            if tick is not None and loop.time() >= next_tick:
                # at most every 50 ms, not per frame: each tick's messages come back as frames, and a tick per
                # frame would snowball into a flood that delays the server's pongs (a keepalive timeout)
                tick()
                next_tick = loop.time() + 0.05
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
        cls = jsonschema.validators.validator_for(schema)
        cls.check_schema(schema)
        validator = cls(schema)   # checked once: jsonschema.validate would check the schema per payload
        payloads = [p for _ts, p in self.data.get(sub_id, [])]
        for p in payloads:
            validator.validate(p)
        return payloads


@contextlib.asynccontextmanager
async def advertised(port: int, topics: set[str], *, tick: Any = None, timeout: float = 60.0) -> AsyncIterator[Client]:
    """A client connected once every topic of *topics* exists, to subscribe to them.

    A first connection waits until the bridge has advertised them all (calling *tick*, a
    publisher, meanwhile), a second one is returned. foxglove-sdk 0.30 can advertise a
    channel created while a client connects and then refuse that client's subscription to it
    ("Unknown channel ID": seen about one run in five on a loaded machine); channels that
    existed before the connection are advertised from the server's snapshot and are safe.
    """
    url = f"ws://127.0.0.1:{port}"
    async with websockets.connect(url, subprotocols=[SUBPROTOCOL]) as ws:
        first = Client(ws)
        await first.pump(lambda: topics <= set(first.channels), timeout=timeout, tick=tick)
    async with websockets.connect(url, subprotocols=[SUBPROTOCOL]) as ws:
        c = Client(ws)
        await c.pump(lambda: topics <= set(c.channels), timeout=timeout, tick=tick)
        yield c


def estimate(i: int) -> t.StateInformation:
    s = t.StateInformation().set(x=10.0 + i * 0.01, y=-5.0, psi=0.5, x_sigma=0.4, y_sigma=0.4)
    s.sensor_name, s.reference_frame = "state_estimator", "NED"
    return s


@pytest.mark.timeout(240)
def test_live_topics_parameters_and_logs(services: ServiceProcesses, bus: Any) -> None:
    proc, err = start_bridge(services, "--allow-parameter-writes")
    port = bridge_port(proc, err)
    services.start("world", "--kind", "world_modeler")
    wait_until(lambda: any(r.name == "world" for r in bus.discover(timeout=0.3)), timeout=30,
               message="the world modeler")
    counter = [0]

    buoy, goal = t.Circle(), t.Waypoint()
    buoy.base.base.uid, buoy.base.base.reference_frame, buoy.base.base.x, buoy.radius = "buoy", "NED", 20.0, 2.0
    goal.base.uid, goal.reference_frame, goal.x, goal.y, goal.horizontal_threshold = "wp1", "LOCAL", 30.0, 5.0, 3.0

    def publish() -> None:
        counter[0] += 1
        bus.publish("STATE_ESTIMATE", estimate(counter[0]))
        bus.publish("WORLD", buoy)
        bus.publish("GOALS", goal)
        edge, write = t.RawGpioEdge(), t.RawGpioWrite()
        edge.device, edge.line, edge.edge = "rc", 3, 1
        write.device, write.line, write.value = "rc", 7, 1
        bus.publish("RAW.rc", edge)
        bus.publish("RAW.rc", write)

    async def session() -> Client:
        wanted = {"STATE_ESTIMATE", "/location/STATE_ESTIMATE", "/tf", "RAW.rc/RawGpioEdge",
                  "RAW.rc/RawGpioWrite", "/log", "/health", "/scene/world", "/scene/mission"}
        async with advertised(port, wanted, tick=publish) as c:
            ws = c.ws
            info = c.replies[0]
            assert info["op"] == "serverInfo" and "parameters" in info["capabilities"]
            assert c.channels["/location/STATE_ESTIMATE"]["schemaName"] == "foxglove.LocationFix"
            assert c.channels["RAW.rc/RawGpioWrite"]["schemaName"] == "u2sa.RawGpioWrite"
            await c.subscribe({1: "/location/STATE_ESTIMATE", 2: "/tf", 3: "RAW.rc/RawGpioEdge",
                               4: "RAW.rc/RawGpioWrite", 5: "/log", 6: "/health", 7: "/scene/world",
                               8: "/scene/mission"})
            # no HSM runs: /health is built from the services' own Health messages (1 s apart; the world
            # summary too): seconds when idle, and a make test run once took over 30 s here
            await c.pump(lambda: all(len(c.data.get(i, [])) >= 3 for i in (1, 2, 3, 4, 7, 8))
                         and any({"world", "foxglove"} <= {r["name"] for r in p["services"]}
                                 for _ts, p in c.data.get(6, [])), timeout=60, tick=publish)
            await ws.send(json.dumps({"op": "getParameters", "parameterNames": [], "id": "all"}))
            await c.pump(lambda: any(r.get("id") == "all" for r in c.replies), timeout=30)
            await ws.send(json.dumps({"op": "setParameters", "id": "set",
                                      "parameters": [{"name": "world.log_level", "value": "debug"}]}))
            await c.pump(lambda: any(r.get("id") == "set" for r in c.replies), timeout=30)
            # the bridge's own reach is not a remote parameter, even with writes allowed
            await ws.send(json.dumps({"op": "setParameters", "id": "host",
                                      "parameters": [{"name": "foxglove.host", "value": "0.0.0.0"}]}))
            await c.pump(lambda: any(r.get("id") == "host" for r in c.replies)
                         and any("foxglove.host" in s["message"] for s in c.status), timeout=30)
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
    got = services.cli("param", "get", "world", "log_level")
    assert got.stdout.strip() == '"debug"', got.stderr
    host = {p["name"]: p["value"] for r in c.replies if r.get("id") == "host" for p in r["parameters"]}
    assert host == {"foxglove.host": "127.0.0.1"}
    (refusal,) = [s["message"] for s in c.status if "foxglove.host" in s["message"]]
    assert "not changed over the bus" in refusal
    for name, value in (("host", "0.0.0.0"), ("allow_parameter_writes", "false"), ("token_file", "t")):
        refused = services.cli("param", "set", "foxglove", name, value)
        assert refused.returncode != 0 and "not changed over the bus" in refused.stderr + refused.stdout, name
    tables = c.validated(6, "/health")
    rows = {r["name"]: r for r in tables[-1]["services"]}
    assert rows["world"]["status"] == "ok" and tables[-1]["summary"].startswith("no HSM heard")
    # (the world modeler's WORLD_SUMMARY does not list the test's buoy: deletions come too)
    world = [e for p in c.validated(7, "/scene/world") for e in p["entities"]][-1]
    assert world["id"] == "object/buoy" and world["cylinders"][0]["pose"]["position"]["y"] == pytest.approx(20.0)
    (wp,) = c.validated(8, "/scene/mission")[-1]["entities"]
    assert wp["id"] == "waypoint/wp1" and wp["spheres"][0]["pose"]["position"]["x"] == pytest.approx(5.0)


@pytest.mark.timeout(60)
def test_parameter_writes_are_refused_unless_allowed(services: ServiceProcesses, bus: Any) -> None:
    """Also: a profile without an origin says in the bridge's health why the Map stays empty."""
    health: dict[str, Any] = {}
    bus.transport.subscribe("U2SA_HEALTH", t.Health, lambda _c, m: health.update(
        last_error=m.last_error, **{kv.key: kv.value for kv in m.details}) if m.name == "foxglove" else None)
    proc, err = start_bridge(services, profile=NO_ORIGIN_PROFILE)
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
    wait_until(lambda: "no [vehicle] origin" in health.get("last_error", ""), timeout=30,
               message="the bridge's health to say there is no origin")
    assert "local positions are not on the map" in health["map"]


@pytest.mark.timeout(60)
def test_parameter_writes_are_refused_on_an_open_bus(services: ServiceProcesses) -> None:
    """allow_parameter_writes on an open (unsigned) bus: a change could not be authenticated, so none is made."""
    proc, err = start_bridge(services, "--allow-parameter-writes", profile=PROFILE + 'bus_security = "open"\n')
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
    assert all(p["value"] == 5000 for p in reply["parameters"])
    assert "the bus is open" in c.status[0]["message"] and "parameters not changed" in c.status[0]["message"]
    assert "allow_parameter_writes is ignored: the bus is open" in err.read_text()


@pytest.mark.timeout(60)
def test_network_exposure_needs_a_token_and_the_gate_checks_it(services: ServiceProcesses, bus: Any) -> None:
    for extra in ([], ["--token-file", "short"]):
        (services.workdir / "short").write_text("too-short\n")
        refused = subprocess.run([*U2SA, "foxglove", "--host", "0.0.0.0", "--port", "0", *extra],
                                 cwd=services.workdir, env=services.env(), capture_output=True, text=True, timeout=30)
        assert refused.returncode != 0 and "Traceback" not in refused.stderr, refused.stderr
        (line,) = [x for x in refused.stderr.splitlines() if x.startswith("u2sa: ")]   # one line says it all
        assert ("token_file" if not extra else "at least 16 characters") in line
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


def test_check_reports_a_network_listener_without_a_good_token(tmp_path: Path) -> None:
    """``u2sa check`` runs the bridge's check_config: no token file, or one too short, is one error line."""
    (tmp_path / "short").write_text("too-short\n")
    (tmp_path / "good").write_text("a-token-long-enough-0123456789\n")
    lines = {}
    for case, settings in (("none", 'host = "0.0.0.0"'), ("short", 'host = "0.0.0.0", token_file = "short"'),
                           ("good", 'host = "0.0.0.0", token_file = "good"'), ("loopback", 'port = 8765')):
        (tmp_path / "vehicle.toml").write_text(f'[vehicle]\nname = "t"\n[services.foxglove]\n'
                                               f'kind = "foxglove_bridge"\nsettings = {{ {settings} }}\n')
        done = subprocess.run([*U2SA, "check", "--vehicle", "vehicle.toml"], cwd=tmp_path, capture_output=True,
                              text=True, timeout=60)
        lines[case] = [x for x in (done.stdout + done.stderr).splitlines() if x.startswith("error:")]
    assert len(lines["none"]) == 1 and "would expose the bus" in lines["none"][0] and "token_file" in lines["none"][0]
    assert len(lines["short"]) == 1 and "at least 16 characters" in lines["short"][0]
    assert lines["good"] == [] and lines["loopback"] == []


def health_msg(name: str, uptime_s: float) -> t.Health:
    msg = t.Health()
    msg.name, msg.status, msg.uptime_s = name, "ok", uptime_s
    return msg


def test_health_table_from_services_own_health_without_an_hsm() -> None:
    """Without a SystemHealth for 3 s (log time), a service's Health sends /health, at most once a second;
    an HSM's SystemHealth always does, and while it is heard the table is its alone."""
    mapper = FoxgloveMapper(origin=None)

    def tables(channel: str, msg: Any, at_s: float) -> list[dict[str, Any]]:
        return [p for topic, p in mapper.map(channel, msg, int(at_s * 1e9)) if topic is HEALTH]

    sent = [at for at, name in ((0.0, "gps"), (0.4, "world"), (1.0, "gps"), (2.1, "world"), (3.0, "gps"),
                                (3.5, "world"), (4.0, "gps"), (4.2, "world"))
            if tables("U2SA_HEALTH", health_msg(name, at), at)]
    assert sent == [3.0, 4.0]
    (table,) = tables("U2SA_HEALTH", health_msg("gps", 5.1), 5.1)
    assert [r["name"] for r in table["services"]] == ["gps", "world"] and table["summary"].startswith("no HSM heard")
    assert table["failsafe"] is None   # no one counts the failsafes held: unknown, not "off"
    system = t.SystemHealth()
    system.summary = "all ok"
    (table,) = tables("U2SA_SYSTEM_HEALTH", system, 5.2)
    assert table["summary"] == "all ok" and table["failsafe"] is False
    assert not tables("U2SA_HEALTH", health_msg("gps", 7.0), 7.0)   # the HSM is heard: its table only
    (table,) = tables("U2SA_HEALTH", health_msg("gps", 8.3), 8.3)   # silent for 3 s: its view is dropped
    assert table["summary"].startswith("no HSM heard") and table["failsafe"] is None


def test_a_geodetic_polygon_is_placed_about_the_origin() -> None:
    """Vertices of a GEODETIC polygon are latitudes and longitudes: the 3D scene gets them in metres."""
    origin = Origin(29.19, -81.05, 10.0)
    corners = [(10.0, 0.0), (10.0, 5.0), (15.0, 5.0)]   # (north, east) m
    geo = [ned_to_geodetic(n, e, 0.0, origin=origin) for n, e in corners]
    poly = t.Polygon()
    base = poly.base.base
    base.uid, base.reference_frame = "reef", "GEODETIC"
    base.x, base.y, base.z = geo[0][0], geo[0][1], origin.alt
    poly.vx, poly.vy = [g[0] for g in geo], [g[1] for g in geo]
    poly.num_vertices = len(geo)
    ((topic, scene),) = [o for o in FoxgloveMapper(origin=origin).map("WORLD", poly, 1) if o[0] is SCENE_WORLD]
    points = scene["entities"][0]["lines"][0]["points"]
    assert [v for p in points[:3] for v in (p["x"], p["y"])] == pytest.approx([0, 10, 5, 10, 5, 15], abs=0.01)
