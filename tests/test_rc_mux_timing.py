"""The RC mux's timing is a function of its input, not of its loop: the driver runs in this process
on a chip with a device clock (as a replay chip is), the same recorded input is played into it
paced three ways (all at once, one event at a time, in uneven chunks), and it publishes the same
RC_MODE and MANUAL_CMD messages each time: the timed ones on the grid of the recorded clock, with
the state as of their due time, the changes at once, and the pre-arm verdicts from the recorded
Health and FAILSAFE handed over by the chip in order with the edges.

Also the pure parts: :class:`u2sa_hw.drivers.rc_mux.pulse.DueGrid` and the filter's signal expiry."""

from __future__ import annotations

import random
import shutil
import tempfile
import threading
from pathlib import Path
from typing import Any, Callable, Iterator

import pytest
import tomli_w
from conftest import wait_until

from u2sa_hw.drivers.rc_mux.pulse import DueGrid, RcModeFilter
from u2sa_hw.mocks.gpio_chip import MockGpioChip
from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.service.health import set_details
from u2sa_hw.messages import enumerate_fields
from u2sa_hw.bus.transport import Transport
from u2sa_hw.bus.udp_ports import private_lcm_url
from u2sa_hw.profile.loader import load_profile

LINES = {"throttle": 5, "steering": 6, "mode": 13}
ENABLE, SELECT = 21, 20
ORIGIN_NS = 7_000_000_123          # the device clock's offset from the recorded clock (a replay chip's)
FRAME_NS = 20_000_000              # 50 Hz
SLOT_NS = FRAME_NS // 3


# ------------------------------------------------------------------ pure logic ---------------------
def test_due_grid_is_fixed_on_the_clock_whatever_asks() -> None:
    grid = DueGrid(20.0)
    assert grid.period_ns == 50_000_000
    assert [grid.after(t) for t in (0, 1, 49_999_999, 50_000_000)] == [50_000_000] * 3 + [100_000_000]
    assert grid.after(123_456_789, origin_ns=7) == 150_000_007          # on the origin's grid
    third = DueGrid(15.0)                                                # a period that is no whole ns
    dues = [third.after(0)]
    for _ in range(14):
        dues.append(third.after(dues[-1]))
    assert dues[-1] == 1_000_000_000 and dues[0] == 66_666_667          # exactly 15 a second, no drift
    assert DueGrid(12.5).after(0) == 80_000_000
    with pytest.raises(ValueError):
        DueGrid(0.0)


def test_signal_expiry_is_the_first_time_check_signal_says_no_signal() -> None:
    f = RcModeFilter(signal_timeout_ns=100_000_000, debounce_frames=1)
    assert f.signal_expiry_ns() is None                 # no frame yet: already "no signal"
    f.on_frame(1000.0, 5_000)
    expiry = f.signal_expiry_ns()
    assert expiry == 100_005_001
    assert not f.check_signal(expiry - 1) and f.check_signal(expiry)
    assert f.signal_expiry_ns() is None


# ------------------------------------------------------------------ the driver in this process -----
def _frame_edges(start_ns: int, widths_us: dict[str, int]) -> list[tuple[int, str, Any]]:
    """One receiver frame: each channel rises at its slot's start and falls after its width."""
    out = []
    for i, name in enumerate(LINES):
        rise = start_ns + i * SLOT_NS
        out += [(rise, "edge", (LINES[name], 1)), (rise + widths_us[name] * 1000, "edge", (LINES[name], 0))]
    return out


def _health(name: str, status: str, **details: str) -> bytes:
    msg = t.Health()
    msg.header.source, msg.name, msg.status = name, name, status
    set_details(msg, details)
    return msg.encode()


def _failsafe(active: bool) -> bytes:
    msg = t.Failsafe()
    msg.header.source, msg.active, msg.reason = "hsm", active, "test failsafe" if active else ""
    return msg.encode()


def recorded_input() -> list[tuple[int, str, Any]]:
    """(recorded time ns, kind, what) in order: the pilot in manual, a throttle change, the switch to
    autonomous with the GPS healthy, a failsafe raised and cleared, a signal loss, back to manual."""
    events: list[tuple[int, str, Any]] = []
    gps_ok = _health("gps", "ok", data="fresh", fix_type="3D", h_sigma_m="1.0", satellites="9")
    base = 1_000_000_000 + 3_333_333          # an odd phase against the 50 ms grid
    events.append((base - 5_000_000, "bus", (ch.HEALTH, _health("gps", "degraded", data="fresh", fix_type="2D"))))
    for k in range(140):
        start = base + k * FRAME_NS
        if k % 25 == 7:
            events.append((start - 1_000_000, "bus", (ch.HEALTH, gps_ok)))
        if k == 60:
            events.append((start + 1_000_000, "bus", (ch.FAILSAFE, _failsafe(True))))
        if k == 68:
            events.append((start + 9_000_000, "bus", (ch.FAILSAFE, _failsafe(False))))
        if 95 <= k < 110:                     # no pulses for 300 ms: the chip's clock ticks through
            for step in range(0, FRAME_NS, 10_000_000):
                events.append((start + step, "tick", None))
            continue
        mode = 2000 if 40 <= k < 80 or 110 <= k < 120 else 1000
        throttle = 1600 if k >= 20 else 1500
        events += _frame_edges(start, {"throttle": throttle, "steering": 1500 + (k % 5), "mode": mode})
    events.sort(key=lambda e: e[0])
    return events


@pytest.fixture
def socket_dir() -> Iterator[Path]:
    path = Path(tempfile.mkdtemp(prefix="u2sa-rct-", dir="/tmp"))  # short: Unix socket paths are limited
    yield path
    shutil.rmtree(path, ignore_errors=True)


def _profile(tmp_path: Path, chip: MockGpioChip) -> Path:
    profile = {
        "vehicle": {"name": "timing", "system_id": 7, "config_dir": "config", "log_dir": "logs", "data_dir": "data"},
        "services": {
            "rc": {"kind": "rc_mux", "settings": {
                "channels": "throttle=5,steering=6,mode=13", "mode_channel": "mode",
                "enable_line": ENABLE, "select_line": SELECT, "publish_hz": 20.0, "manual_hz": 25.0,
                "signal_timeout_ms": 100.0}},
            "gps": {"kind": "gps_nmea"},
            "wheels": {"kind": "odrive_can", "settings": {"actuators": ["left_wheel", "right_wheel"]}},
        },
        "devices": {"rc": {"address": f"mock+gpio://{chip.socket_path}"}},
        "safety": {"manual_mixer": {"kind": "differential", "left": "left_wheel", "right": "right_wheel",
                                    "throttle_channel": "throttle", "steering_channel": "steering"},
                   "prearm": {"gps": {"max_sigma_m": 5.0}, "required_services": {"ignore": ["wheels"]}}},
    }
    path = tmp_path / "vehicle.toml"
    path.write_text(tomli_w.dumps(profile))
    return path


def run_driver(tmp_path: Path, socket_dir: Path, feed: Callable[[MockGpioChip, Any, list], None]) -> list:
    """The RC mux driver on a fresh device-clock chip, the recorded input fed by *feed*; what it published."""
    from u2sa_hw.drivers.rc_mux.driver import RcMuxDriver

    chip = MockGpioChip(socket_path=str(socket_dir / "gpio.sock"), release_level=None, device_clock=True).start()
    for line in LINES.values():
        chip.drive_input(line, 0)
    published: list[tuple[str, dict[str, Any]]] = []
    transport = Transport(private_lcm_url(), name="rc-timing-test")   # never started: publish is captured
    profile = load_profile(_profile(tmp_path, chip))
    driver = RcMuxDriver("rc", profile=profile, settings=profile.services["rc"].settings, transport=transport)
    events = recorded_input()
    last = events[-1][0] + ORIGIN_NS

    def capture(channel: str, msg: Any, **_: Any) -> bool:
        if driver.clock_ns is None or driver.clock_ns <= last:   # not what a 2 s silent chip's clock adds after
            published.append((channel, {k: v for k, v in enumerate_fields(msg) if "header" not in k}))
        return True

    driver.publish = capture  # type: ignore[method-assign]
    driver.running = True
    loop = threading.Thread(target=driver.run, daemon=True)
    loop.start()
    try:
        wait_until(lambda: chip.consumers() and driver._recorded_bus, message="the driver holding its lines and "
                                                                               "asking for the recorded bus")
        chip.set_origin(ORIGIN_NS)
        feed(chip, driver, events)
        # one tick past the input: once the driver's clock is there, all it did at the last stamp is done
        # (one loop, in stamp order); what it publishes at the tick is past *last*, so not captured
        chip.tick(last + 1)
        wait_until(lambda: driver.clock_ns is not None and driver.clock_ns > last, timeout=30,
                   message="the driver taking the whole input")
    finally:
        driver.stop()
        loop.join(timeout=5)
        driver.gpio.close()
        chip.stop()
    return published


def _send(chip: MockGpioChip, event: tuple[int, str, Any]) -> None:
    stamp, kind, what = event[0] + ORIGIN_NS, event[1], event[2]
    if kind == "edge":
        chip.drive_input(what[0], what[1], stamp)
    elif kind == "tick":
        chip.tick(stamp)
    else:
        assert chip.bus(stamp, what[0], what[1]) == 1, "the driver asked for the recorded bus"


def all_at_once(chip: MockGpioChip, driver: Any, events: list) -> None:
    for event in events:
        _send(chip, event)


def one_by_one(chip: MockGpioChip, driver: Any, events: list) -> None:
    for event in events:
        _send(chip, event)
        if event[1] == "bus":    # a bus input does not move the driver's clock
            wait_until(lambda: chip.backlog() == 0, timeout=30, interval=0.0005, message="the chip sending it")
            continue
        stamp = event[0] + ORIGIN_NS
        wait_until(lambda stamp=stamp: driver.clock_ns is not None and driver.clock_ns >= stamp, timeout=30,
                   interval=0.0005, message="the driver taking the event")


def in_uneven_chunks(chip: MockGpioChip, driver: Any, events: list) -> None:
    rng = random.Random(14)
    i = 0
    while i < len(events):
        n = rng.choice((1, 2, 3, 7, 40, 150))
        for event in events[i:i + n]:
            _send(chip, event)
        i += n
        if rng.random() < 0.5:   # now and then the chip delivers before the next chunk is queued
            wait_until(lambda: chip.backlog() == 0, timeout=30, interval=0.0005, message="the chip sending it")


def test_the_same_recorded_input_paced_three_ways_gives_the_same_messages(tmp_path: Path, socket_dir: Path) -> None:
    runs = {}
    for name, feed in (("all at once", all_at_once), ("one by one", one_by_one), ("uneven", in_uneven_chunks)):
        sub = tmp_path / name.replace(" ", "-")
        sub.mkdir()
        runs[name] = run_driver(sub, socket_dir, feed)
    reference = runs["all at once"]
    for name, got in runs.items():
        assert len(got) == len(reference), f"{name}: {len(got)} messages against {len(reference)}"
        for i, (a, b) in enumerate(zip(reference, got)):
            assert a == b, f"{name}: message {i} differs: {a} against {b}"

    modes = [fields for channel, fields in reference if channel == ch.RC_MODE]
    manual = [fields for channel, fields in reference if channel == ch.MANUAL_CMD]
    # the pilot's input, measured from the stamps; then autonomy granted once the GPS health says 3D
    assert any(m["mode"] == 0 and m["pulse_us"] == [1600, 1502, 1000] for m in modes)
    assert any(m["mode"] == 1 and m["autonomy_enabled"] and not m["blocked_by"] for m in modes)
    # the recorded FAILSAFE, handed over with the edges: autonomy dropped, and not back before a re-arm
    blocked = [m["blocked_by"] for m in modes]
    assert any(b.startswith("failsafe (") for b in blocked)
    assert any("not armed" in b for b in blocked)
    # the signal loss: no signal at the recorded moment, and the sticks' commands only in manual
    assert any(m["mode"] == 2 and m["pulse_us"] == [0, 0, 0] for m in modes)
    assert manual and all(cmd["base.actuator_name"] in ("left_wheel", "right_wheel") for cmd in manual)
    # about one timed RC_MODE per 50 ms of recorded time, plus the changes
    span_s = (recorded_input()[-1][0] - recorded_input()[0][0]) / 1e9
    assert span_s * 20 - 2 <= len(modes) <= span_s * 20 + 25
