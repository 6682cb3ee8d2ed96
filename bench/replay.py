#!/usr/bin/env python3
"""Replay and recorder benchmark.

1. Replay speed: writes a synthetic driver-level log of ``--minutes`` (default 10) -- the mock
   GPS's NMEA at 10 Hz (115200 baud) and the mock compass's HDG+XDR at 10 Hz (19200 baud) as
   ``RawSerial`` chunks, one per line, stamped with when its last byte would arrive at that
   baud rate, plus the STATE_INFO the drivers publish for them (built with the drivers' own
   parsing functions) -- then replays it with ``--fast`` against the real drivers and prints
   the speed-up over real time (aim: 20x) and the comparison with the recorded outputs.
2. Recorder throughput: a publisher process sends the example ground vehicle's channel mix
   at ``--factor`` (default 10) times its nominal rates for ``--seconds``; the recorder's
   BusCapture in this process writes it to MCAP. Prints the rate achieved, what never reached
   the recorder and what it dropped (its queue overflowing).

Usage: ``python bench/replay.py [--minutes 10] [--factor 10] [--seconds 10] [--skip-replay|--skip-recorder]``
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import tomli_w

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from drivers.compass_serial import reading_from_epoch, state_from_reading  # noqa: E402
from drivers.gps_fix import StateSettings, fix_from_epoch, state_from_fix  # noqa: E402
from drivers.nmea_fields import EpochCollector, parse_sentence  # noqa: E402
from mock_devices.nmea_gps import NmeaGpsDevice  # noqa: E402
from mock_devices.serial_compass import NmeaCompassDevice  # noqa: E402
from mock_devices.vehicle_sim import SimVehicle  # noqa: E402
from u2sa_hw.bus_key import use_run_key  # noqa: E402
from u2sa_hw import lcmtypes as t  # noqa: E402
from u2sa_hw.recording.mcap_log import McapLogWriter, RunInfo  # noqa: E402
from u2sa_hw.vehicle import Origin  # noqa: E402
from u2sa_hw.udp_ports import private_lcm_url  # noqa: E402

ORIGIN = Origin(29.1895, -81.0483, 10.0)
GPS_BAUD, COMPASS_BAUD = 115200, 19200
EPOCH_GAP_S = 0.05  # the drivers' default epoch_gap_s: their output follows a burst by this much

# The example ground vehicle (examples/ground_vehicle) with every driver's record_raw on:
# channel -> (messages per second, payload bytes). Rates from its configs: gps 5 Hz, compass
# 10 Hz, IMU 50 Hz, ODrive encoder estimates 100 Hz per axis, estimator 50 Hz, control and
# planner 20 Hz, RC 10 Hz, health 1 Hz per service; raw taps: NMEA lines, I2C burst reads,
# CAN frames both ways, PWM writes at the servo's 50 Hz, RC pulse edges (3 channels, 50 Hz).
EXAMPLE_RATES: dict[str, tuple[float, int]] = {
    "STATE_INFO": (5 + 10 + 50 + 100, 440), "STATE_ESTIMATE": (50, 440), "ACTUATOR_CMD": (40, 80),
    "NAV_POINT": (20, 120), "RC_MODE": (10, 60), "GOALS": (1, 200), "MISSION_STATUS": (1, 120),
    "WORLD": (2, 300), "WORLD_SUMMARY": (2, 100), "U2SA_HEALTH": (12, 600), "U2SA_SYSTEM_HEALTH": (1, 800),
    "RAW.gps": (30, 110), "RAW.compass": (20, 80), "RAW.imu": (100, 70), "RAW.wheels": (460, 70),
    "RAW.pan": (50, 60), "RAW.rc": (300, 60),
}


def _state(source: str, seq: int, msg: t.StateInformation, received: float) -> bytes:
    msg.sensor_name = source
    msg.reference_frame = msg.reference_frame or "NED"
    msg.header.system_id, msg.header.source, msg.header.sequence = 1, source, seq
    msg.header.timestamp_us = int(received * 1e6)
    return msg.encode()


def _raw(device: str, data: bytes, t_s: float) -> bytes:
    rec = t.RawSerial()
    rec.device, rec.direction, rec.data, rec.length = device, 0, data, len(data)
    rec.header.system_id, rec.header.source, rec.header.timestamp_us = 1, device, int(t_s * 1e6)
    return rec.encode()


def synthetic_log(path: Path, *, minutes: float, gps_hz: float = 10.0, compass_hz: float = 10.0) -> int:
    """Write the driver-level log; returns its message count."""
    tmp = Path(tempfile.mkdtemp(prefix="u2sa-bench-"))
    vehicle = SimVehicle(origin_lat=ORIGIN.lat, origin_lon=ORIGIN.lon, origin_alt=ORIGIN.alt)
    vehicle.set_wheel_speed("left", 1.2)
    vehicle.set_wheel_speed("right", 1.5)   # a wide circle
    t0 = time.time()
    clock = [t0]
    gps = NmeaGpsDevice(vehicle, link_path=tmp / "gps", rate_hz=gps_hz, seed=1,
                        sentences=("GGA", "RMC", "VTG", "GSA", "GST", "HDT"),
                        utc_clock=lambda: dt.datetime.fromtimestamp(clock[0], dt.timezone.utc))
    compass = NmeaCompassDevice(vehicle, link_path=tmp / "compass", rate_hz=compass_hz, sentences=("HDG", "XDR"),
                                seed=2)
    profile = {"vehicle": {"name": "bench", "system_id": 1, "origin": {"lat": ORIGIN.lat, "lon": ORIGIN.lon,
                                                                        "alt": ORIGIN.alt}},
               "services": {"gps": {"kind": "gps_nmea", "settings": {"port": "/dev/u2sa/gps", "baudrate": GPS_BAUD,
                                                                     "record_raw": True}},
                            "compass": {"kind": "compass_serial", "settings": {
                                "port": "/dev/u2sa/compass", "baudrate": COMPASS_BAUD, "record_raw": True}}}}
    writer = McapLogWriter(path.parent, path=path, run=RunInfo(
        vehicle="bench", system_id=1, attachments={"vehicle.toml": tomli_w.dumps(profile).encode()}))
    settings = StateSettings(origin=ORIGIN)
    events: list[tuple[float, str, bytes]] = []
    seq = {"gps": 0, "compass": 0}

    def burst(device: str, lines: list[bytes], start: float, baud: int) -> None:
        collector = EpochCollector()
        sent = 0
        for line in lines:
            sent += len(line)
            arrival = start + sent * 10.0 / baud
            events.append((arrival, f"RAW.{device}", _raw(device, line, arrival)))
            sentence = parse_sentence(line)
            if sentence is not None:
                collector.add(sentence, received=start + len(lines[0]) * 10.0 / baud)
        epoch = collector.flush()
        if epoch is None:
            return
        if device == "gps":
            msg = state_from_fix(fix_from_epoch(epoch), settings)
        else:
            msg = state_from_reading(reading_from_epoch(epoch, declination_deg=0.0, use_hdg_variation=True),
                                     heading_sigma_deg=1.0, attitude_sigma_deg=0.5)
        if msg is not None:
            seq[device] += 1
            events.append((start + sent * 10.0 / baud + EPOCH_GAP_S, "STATE_INFO",
                           _state("gps" if device == "gps" else "compass", seq[device], msg, epoch.received)))

    step = 0.01
    next_gps, next_compass = t0, t0 + 0.003
    while clock[0] < t0 + minutes * 60.0:
        clock[0] += step
        vehicle.step(step)
        if clock[0] >= next_gps:
            burst("gps", gps.epoch_lines(vehicle.snapshot()), clock[0], GPS_BAUD)
            next_gps += 1.0 / gps_hz
        if clock[0] >= next_compass:
            burst("compass", compass.epoch_lines(vehicle.snapshot()), clock[0], COMPASS_BAUD)
            next_compass += 1.0 / compass_hz
        if len(events) > 5000:
            _flush(writer, events, upto=clock[0] - 1.0)
    _flush(writer, events, upto=float("inf"))
    writer.close()
    return writer.messages


def _flush(writer: McapLogWriter, events: list[tuple[float, str, bytes]], *, upto: float) -> None:
    """Write the events before *upto* in time order (bursts of the two devices interleave)."""
    events.sort(key=lambda e: e[0])
    keep = [e for e in events if e[0] >= upto]
    for when, channel, data in (e for e in events if e[0] < upto):
        writer.write(channel, data, int(when * 1e9))
    events[:] = keep


def bench_replay(minutes: float) -> None:
    """Part 1: the synthetic log replayed with --fast."""
    from hil.compare import compare_logs
    from hil.replay import Replay, ReplayOptions

    work = Path(tempfile.mkdtemp(prefix="u2sa-bench-replay-"))
    log = work / "synthetic.mcap"
    t_gen = time.monotonic()
    count = synthetic_log(log, minutes=minutes)
    print(f"synthetic log: {minutes:g} min, {count} messages, {log.stat().st_size / 1e6:.1f} MB, "
          f"written in {time.monotonic() - t_gen:.1f} s")
    started = time.monotonic()
    result = Replay(log, ReplayOptions(fast=True, out=work / "replayed.mcap", progress=False)).run()
    total = time.monotonic() - started
    played = result.plan.duration_s
    print(result.summary(fast=True, rate=1.0))
    print(f"replay --fast: {played:.0f} s of log in {result.play.wall_s:.1f} s of playback = "
          f"{played / result.play.wall_s:.1f}x real time (aim >= 20x); {total:.1f} s in all with "
          f"{result.startup_s:.1f} s starting the services and the wait for the last outputs "
          f"= {played / total:.1f}x end to end; {result.play.records} device writes")
    report = compare_logs(log, result.out, services=set(result.plan.services), rate=None)
    print(report.format())
    shutil.rmtree(work, ignore_errors=True)


def publisher(url: str, factor: float, seconds: float) -> None:
    """Child process: publish the example vehicle's mix at *factor* times its rates; print the count sent."""
    from u2sa_hw.transport import Transport

    tx = Transport(url, name="bench-publisher")   # signed, as every u2sa publisher is
    plan = [(ch, rate * factor, b"\x00" * size) for ch, (rate, size) in EXAMPLE_RATES.items()]
    sent = 0
    start = time.monotonic()
    credit = {ch: 0.0 for ch, _, _ in plan}
    tick = 0.002
    while (now := time.monotonic()) - start < seconds:
        for ch, rate, payload in plan:
            due = rate * (now - start) - credit[ch]
            while due >= 1.0:
                tx.publish_bytes(ch, payload)
                credit[ch] += 1.0
                due -= 1.0
                sent += 1
        time.sleep(max(0.0, tick - (time.monotonic() - now)))
    print(sent, flush=True)


def bench_recorder(factor: float, seconds: float) -> None:
    """Part 2: the recorder's capture under the example vehicle's mix times *factor*."""
    from u2sa_hw.services.recorder.capture import BusCapture
    from u2sa_hw.transport import Transport

    nominal = sum(r for r, _ in EXAMPLE_RATES.values())
    url = private_lcm_url(options="ttl=0&recv_buf_size=4194304")
    work = Path(tempfile.mkdtemp(prefix="u2sa-bench-recorder-"))
    transport = Transport(url, name="bench-recorder")
    writer = McapLogWriter(work, path=work / "throughput.mcap", run=RunInfo(vehicle="bench"))
    capture = BusCapture(transport, writer, min_free_mb=50)
    capture.start()
    transport.start()
    child = subprocess.run([sys.executable, __file__, "--publisher", url, str(factor), str(seconds)],
                           capture_output=True, text=True, timeout=seconds + 60, env=dict(os.environ))
    deadline = time.monotonic() + 5.0
    while capture.queue_depth and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.3)
    capture.stop()
    transport.stop()
    sent = int(child.stdout.strip() or 0)
    s = capture.stats
    print(f"recorder: example vehicle mix {nominal:.0f} msg/s x {factor:g} = {nominal * factor:.0f} msg/s target "
          f"on {len(EXAMPLE_RATES)} channels for {seconds:g} s")
    print(f"  sent {sent} ({sent / seconds:.0f} msg/s achieved by the publisher); the recorder received {s.received} "
          f"and wrote {s.written} ({s.written / seconds:.0f} msg/s), dropped {s.dropped} (its queue full); "
          f"{sent - s.received} never reached it; file {writer.files[0].stat().st_size / 1e6:.1f} MB")
    shutil.rmtree(work, ignore_errors=True)


def main() -> int:
    """Run the benchmarks."""
    if len(sys.argv) == 5 and sys.argv[1] == "--publisher":
        publisher(sys.argv[2], float(sys.argv[3]), float(sys.argv[4]))
        return 0
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--minutes", type=float, default=10.0, help="synthetic log length (default 10)")
    p.add_argument("--factor", type=float, default=10.0, help="times the example vehicle's rates (default 10)")
    p.add_argument("--seconds", type=float, default=10.0, help="recorder test length (default 10)")
    p.add_argument("--skip-replay", action="store_true")
    p.add_argument("--skip-recorder", action="store_true")
    args = p.parse_args()
    use_run_key()
    if not args.skip_replay:
        bench_replay(args.minutes)
    if not args.skip_recorder:
        bench_recorder(args.factor, args.seconds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
