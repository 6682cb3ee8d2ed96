#!/usr/bin/env python3
"""The live Foxglove bridge's cost: its CPU and the latency it adds, streaming the example vehicle's channels.

A publisher process sends the example ground vehicle's channel mix (the mix of
``bench/replay.py``, every raw tap on) at ``--factor`` times its rates, as real, decodable
messages of each channel's types, signed like every u2sa publisher. ``u2sa foxglove``
runs as its own process. Two phases of ``--seconds`` each:

1. **No client**: the bridge decodes and maps everything, but builds no JSON (nobody
   subscribed). Its CPU % (of one core, user + system time over the window, psutil).
2. **A client subscribed to every topic** (the worst case: every panel open), a real
   WebSocket client (``websockets``) in this process. The bridge's CPU %, the messages
   the client received, and for STATE_ESTIMATE the latency from publish (the header's
   timestamp, set just before publishing) to the client's receipt, beside the same
   latency measured by a plain LCM subscriber in this process: the difference is what
   the bridge adds (queue, decode, JSON, WebSocket). Also the bridge's own drop count
   and largest queue wait, from its health.

Usage: ``python bench/foxglove.py [--seconds 15] [--factor 1]``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import psutil

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from u2sa_hw import lcmtypes as t  # noqa: E402
from u2sa_hw.bus.run_keys import use_run_key  # noqa: E402
from u2sa_hw.bus.udp_ports import private_lcm_url  # noqa: E402
from example_mix import EXAMPLE_RATES  # noqa: E402  (bench/ is the script's directory)



def sample(channel: str) -> Any:
    """A message of the kind the example vehicle sends on *channel*."""
    if channel in ("STATE_INFO", "STATE_ESTIMATE"):
        m = t.StateInformation().set(x=12.0, y=-3.0, psi=0.7, x_dot=1.5, y_dot=0.2, x_sigma=0.3, y_sigma=0.3)
        m.sensor_name, m.reference_frame = "state_estimator", "NED"
    elif channel == "ACTUATOR_CMD":
        m = t.PercentageCommand()
        m.base.actuator_name, m.percentage = "left_wheel", 42.0
    elif channel == "NAV_POINT":
        m = t.NavigationPoint()
        m.goal_uid, m.x, m.y, m.speed, m.distance_to_goal = "wp1", 20.0, 0.0, 2.0, 8.0
    elif channel == "RC_MODE":
        m = t.RcMode()
        m.mode_name, m.autonomy_enabled = "autonomous", True
    elif channel == "GOALS":
        m = t.Waypoint()
        m.base.uid, m.reference_frame, m.x, m.y, m.horizontal_threshold = "wp1", "LOCAL", 20.0, 0.0, 2.0
    elif channel == "MISSION_STATUS":
        m = t.MissionStatus()
        m.mission_name, m.current_uid = "bench", "wp1"
    elif channel == "WORLD":
        m = t.Circle()
        m.base.base.uid, m.base.base.reference_frame, m.base.base.x, m.radius = "tree", "NED", 20.0, 1.5
    elif channel == "WORLD_SUMMARY":
        m = t.WorldSummary()
        m.uids, m.num_objects = ["tree"], 1
    elif channel == "U2SA_HEALTH":
        m = t.Health()
        m.name, m.status, m.uptime_s = "gps", "ok", 10.0
    elif channel == "U2SA_SYSTEM_HEALTH":
        m = t.SystemHealth()
        m.summary = "all ok"
    elif channel == "RAW.imu":
        m = t.RawI2c()
        m.device, m.data, m.length = "imu", b"\x01" * 14, 14
    elif channel == "RAW.wheels":
        m = t.RawCanFrame()
        m.device, m.arbitration_id, m.data, m.length, m.dlc = "wheels", 0x9, b"\x00" * 8, 8, 8
    elif channel == "RAW.pan":
        m = t.RawPwmWrite()
        m.device, m.period_ns, m.duty_ns, m.enabled = "pan", 20_000_000, 1_500_000, True
    elif channel == "RAW.rc":
        m = t.RawGpioEdge()
        m.device, m.line, m.edge = "rc", 5, 1
    else:
        m = t.RawSerial()
        line = b"$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47\r\n"
        m.device, m.data, m.length = channel.split(".", 1)[-1], line, len(line)
    return m


def publisher(url: str, factor: float, seconds: float) -> None:
    """Child process: publish the mix; STATE_ESTIMATE carries its publish time in the header."""
    from u2sa_hw.bus.transport import Transport

    tx = Transport(url, name="bench-publisher")
    plan = [(ch, rate * factor, sample(ch)) for ch, (rate, _size) in EXAMPLE_RATES.items()]
    start = time.monotonic()
    credit = {ch: 0.0 for ch, _, _ in plan}
    sent = 0
    while (now := time.monotonic()) - start < seconds:
        for ch, rate, msg in plan:
            due = rate * (now - start) - credit[ch]
            while due >= 1.0:
                root = msg.header if hasattr(msg, "header") else msg.base.header if hasattr(msg.base, "header") \
                    else msg.base.base.header
                root.timestamp_us = time.time_ns() // 1000
                tx.publish(ch, msg)
                credit[ch] += 1.0
                due -= 1.0
                sent += 1
        time.sleep(max(0.0, 0.002 - (time.monotonic() - now)))
    print(sent, flush=True)


def cpu_seconds(proc: psutil.Process) -> float:
    c = proc.cpu_times()
    return c.user + c.system


async def client(port: int, seconds: float, latencies: list[float]) -> int:
    import websockets

    received = 0
    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"],
                                  max_size=None) as ws:
        channels: dict[int, str] = {}
        subscribed: set[int] = set()
        loop = asyncio.get_running_loop()
        end = loop.time() + seconds
        while loop.time() < end:
            try:
                frame = await asyncio.wait_for(ws.recv(), 0.2)
            except asyncio.TimeoutError:
                continue
            now_us = time.time_ns() // 1000
            if isinstance(frame, bytes):
                received += 1
                _op, sub_id, _ts = struct.unpack_from("<BIQ", frame)
                if channels.get(sub_id) == "STATE_ESTIMATE":
                    latencies.append((now_us - json.loads(frame[13:])["header"]["timestamp_us"]) / 1000.0)
                continue
            msg = json.loads(frame)
            if msg["op"] == "advertise":
                new = [c for c in msg["channels"] if c["id"] not in subscribed]
                for c in new:
                    channels[c["id"]] = c["topic"]   # subscription id = channel id
                    subscribed.add(c["id"])
                if new:
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                        {"id": c["id"], "channelId": c["id"]} for c in new]}))
    return received


def percentiles(values: list[float]) -> str:
    if not values:
        return "no samples"
    q = statistics.quantiles(values, n=100) if len(values) > 1 else [values[0]] * 99
    return f"p50 {q[49]:.2f} ms, p95 {q[94]:.2f} ms, max {max(values):.2f} ms ({len(values)} samples)"


def main() -> int:
    """Run both phases and print the figures."""
    if len(sys.argv) == 5 and sys.argv[1] == "--publisher":
        publisher(sys.argv[2], float(sys.argv[3]), float(sys.argv[4]))
        return 0
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=15.0, help="length of each phase (default 15)")
    p.add_argument("--factor", type=float, default=1.0, help="times the example vehicle's rates (default 1)")
    args = p.parse_args()
    use_run_key()
    from u2sa_hw.bus.transport import Transport

    url = private_lcm_url()
    env = dict(os.environ, U2SA_LCM_URL=url, PYTHONPATH=str(REPO))
    work = Path(tempfile.mkdtemp(prefix="u2sa-bench-foxglove-"))
    err = work / "bridge.stderr"
    bridge = subprocess.Popen([sys.executable, "-m", "u2sa_hw.cli", "foxglove", "--port", "0", "--no-logs"], cwd=work,
                              env=env, stdout=subprocess.DEVNULL, stderr=open(err, "wb"))
    health: dict[str, str] = {}
    direct: list[float] = []
    listener = Transport(url, name="bench-listener")
    listener.subscribe("U2SA_HEALTH", t.Health, lambda _c, m: health.update(
        {kv.key: kv.value for kv in m.details}) if m.name == "foxglove" else None)
    listener.subscribe("STATE_ESTIMATE", t.StateInformation, lambda _c, m: direct.append(
        (time.time_ns() // 1000 - m.header.timestamp_us) / 1000.0))
    listener.start()
    try:
        deadline = time.monotonic() + 30
        while not (m := re.search(r"ws://127.0.0.1:(\d+)", err.read_text())):
            if time.monotonic() > deadline or bridge.poll() is not None:
                print(err.read_text(), file=sys.stderr)
                return 1
            time.sleep(0.1)
        port = int(m.group(1))
        proc = psutil.Process(bridge.pid)
        nominal = sum(r for r, _ in EXAMPLE_RATES.values()) * args.factor
        total = 2 * args.seconds + 2
        pub = subprocess.Popen([sys.executable, __file__, "--publisher", url, str(args.factor), str(total)],
                               stdout=subprocess.PIPE, text=True, env=env)
        time.sleep(1.0)   # the publisher up to speed
        c0, w0 = cpu_seconds(proc), time.monotonic()
        time.sleep(args.seconds)
        idle_cpu = 100.0 * (cpu_seconds(proc) - c0) / (time.monotonic() - w0)
        health_idle = dict(health)
        direct.clear()
        latencies: list[float] = []
        c0, w0 = cpu_seconds(proc), time.monotonic()
        received = asyncio.run(client(port, args.seconds, latencies))
        busy_cpu = 100.0 * (cpu_seconds(proc) - c0) / (time.monotonic() - w0)
        time.sleep(1.2)   # one more health message from the bridge
        sent = int(pub.communicate(timeout=total + 30)[0].strip() or 0)
    finally:
        listener.stop()
        bridge.terminate()
        bridge.wait(timeout=10)
    print(f"foxglove bridge: example vehicle mix {nominal:.0f} msg/s on {len(EXAMPLE_RATES)} channels, "
          f"{args.seconds:g} s per phase, publisher sent {sent}")
    print(f"  no client:                 bridge CPU {idle_cpu:5.1f} % of one core "
          f"(received {health_idle.get('received', '?')}, dropped {health_idle.get('dropped', '?')})")
    print(f"  client on every topic:     bridge CPU {busy_cpu:5.1f} % of one core, client got {received} messages "
          f"({received / args.seconds:.0f}/s); bridge dropped {health.get('dropped', '?')}, "
          f"largest queue wait {health.get('max_delay_ms', '?')} ms in its last second")
    print(f"  STATE_ESTIMATE latency, publish -> Foxglove client: {percentiles(latencies)}")
    print(f"  STATE_ESTIMATE latency, publish -> plain LCM subscriber: {percentiles(direct)}")
    if latencies and direct:
        print(f"  added by the bridge (median): {statistics.median(latencies) - statistics.median(direct):.2f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
