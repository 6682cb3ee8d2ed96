"""GPIO port: one contract suite over every chip backend that can run here, and the gpiod
backend's error paths (this machine has no /dev/gpiochip*).

Backends of the contract: the mock chip in this process; the mock chip in another process
(driven through a small stdin/stdout control script), so the port is exercised over a real
Unix socket between processes; and the gpiod backend (``GpiodGpioPort``, libgpiod v2's
own LineSettings, enums and errors) with libgpiod's two kernel calls answered by a mock
chip (u2sa_hw.mocks.gpiod_on_mock). The kernel's gpio-sim would give the gpiod backend a
real kernel chip, but it needs configfs (/sys/kernel/config/gpio-sim), which this machine
does not have.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Iterator

import gpiod
import pytest

from conftest import REPO, wait_until
from u2sa_hw.mocks.gpio_chip import MockGpioChip
from u2sa_hw.mocks.gpiod_on_mock import GpiodOnMockChips
from u2sa_hw.ports.errors import PortClosed, PortUnavailable
from u2sa_hw.ports.gpio.wire import EdgeEvent
from u2sa_hw.ports.gpio.gpiod_backend import GpiodGpioPort
from u2sa_hw.ports.gpio.port import GpioPort, open_gpio

CHIP_PROCESS = r"""
import sys
from u2sa_hw.mocks.gpio_chip import MockGpioChip
chip = MockGpioChip(socket_path=sys.argv[1]).start()
print("ready", flush=True)
for command in sys.stdin:
    name, *args = command.split()
    if name == "drive":
        chip.drive_input(int(args[0]), int(args[1]), int(args[2]))
        print("ok", flush=True)
    elif name == "out":
        print(chip.read_output(int(args[0])), flush=True)
chip.stop()
"""


class InProcessChip:
    """The contract's view of a chip: address, drive an input, read an output, go away."""

    def __init__(self, path: Path) -> None:
        self.chip = MockGpioChip(socket_path=str(path)).start()
        self.address = self.chip.address

    def drive(self, line: int, value: int, timestamp_ns: int) -> None:
        self.chip.drive_input(line, value, timestamp_ns)

    def read_output(self, line: int) -> int:
        return self.chip.read_output(line)

    def vanish(self) -> None:
        self.chip.stop()


class ChildProcessChip:
    """The same chip served by another process."""

    def __init__(self, path: Path) -> None:
        env = dict(os.environ, PYTHONPATH=str(REPO))
        self.proc = subprocess.Popen([sys.executable, "-c", CHIP_PROCESS, str(path)], cwd=REPO, env=env,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout.readline().strip() == "ready"
        self.address = f"mock:{path}"

    def _ask(self, command: str) -> str:
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()
        return self.proc.stdout.readline().strip()

    def drive(self, line: int, value: int, timestamp_ns: int) -> None:
        assert self._ask(f"drive {line} {value} {timestamp_ns}") == "ok"

    def read_output(self, line: int) -> int:
        return int(self._ask(f"out {line}"))

    def vanish(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(timeout=10)


class GpiodOnMockChip(InProcessChip):
    """The gpiod backend: the port opens /dev/gpiochip7 through libgpiod, whose kernel calls a mock chip answers."""

    PATH = "/dev/gpiochip7"

    def __init__(self, path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        super().__init__(path)
        fake = GpiodOnMockChips()
        fake.attach(self.PATH, self.chip)
        monkeypatch.setattr(gpiod, "request_lines", fake.request_lines)
        monkeypatch.setattr(gpiod, "Chip", fake.Chip)
        self.address = self.PATH


@pytest.fixture(params=["mock-in-process", "mock-other-process", "gpiod-on-mock"])
def chip(request: pytest.FixtureRequest, tmp_path: Path,
         monkeypatch: pytest.MonkeyPatch) -> Iterator[InProcessChip | ChildProcessChip]:
    if request.param == "gpiod-on-mock":
        backend: InProcessChip | ChildProcessChip = GpiodOnMockChip(tmp_path / "gpio.sock", monkeypatch)
    else:
        backend = (InProcessChip if request.param == "mock-in-process" else ChildProcessChip)(tmp_path / "gpio.sock")
    yield backend
    backend.vanish()


def read_until(port: GpioPort, count: int, *, timeout: float = 5.0) -> list[EdgeEvent]:
    """Collect edges until *count* have arrived (fails the test after *timeout*)."""
    events: list[EdgeEvent] = []
    wait_until(lambda: events.extend(port.read_edges(0.05)) or len(events) >= count, timeout=timeout,
               message=f"{count} edges")
    return events


def test_outputs_start_at_their_initial_value_and_follow_set(chip) -> None:
    port = open_gpio(device="lights", chip=chip.address, outputs={17: 1, 18: 0})
    assert isinstance(port, GpiodGpioPort) == isinstance(chip, GpiodOnMockChip)
    assert (chip.read_output(17), chip.read_output(18)) == (1, 0)
    port.set(18, 1)
    port.set(17, 0)
    assert (chip.read_output(17), chip.read_output(18)) == (0, 1)
    assert (port.get(17), port.get(18)) == (0, 1)
    port.close()


def test_edges_carry_the_chip_timestamps_not_the_reception_time(chip) -> None:
    port = open_gpio(device="rc", chip=chip.address, inputs=[5, 6])
    base = time.monotonic_ns() - 10_000_000_000  # ten seconds ago: nothing a reader could stamp
    chip.drive(5, 1, base)
    chip.drive(6, 1, base + 250)
    chip.drive(5, 0, base + 1_500_000)
    events = read_until(port, 3)
    assert events == [EdgeEvent(5, True, base), EdgeEvent(6, True, base + 250), EdgeEvent(5, False, base + 1_500_000)]
    assert (port.get(5), port.get(6)) == (0, 1)
    port.close()


def test_rising_edge_detection_reports_only_rising_edges(chip) -> None:
    port = open_gpio(device="wheel", chip=chip.address, inputs=[3], edge="rising")
    for i in range(6):
        chip.drive(3, 1 - i % 2, 1_000 + i)
    events = read_until(port, 3)
    assert [(e.rising, e.timestamp_ns) for e in events] == [(True, 1_000), (True, 1_002), (True, 1_004)]
    assert port.read_edges(0.1) == []
    port.close()


def test_taps_see_every_edge_with_its_timestamp_and_every_write(chip) -> None:
    records = []
    port = open_gpio(device="mux", chip=chip.address, inputs=[20], outputs={21: 0}, tap=records.append)
    port.set(21, 1)
    chip.drive(20, 1, 123_456_789)
    read_until(port, 1)
    kinds = [(type(r).__name__, r.device, r.line) for r in records]
    assert kinds == [("RawGpioWrite", "mux", 21), ("RawGpioWrite", "mux", 21), ("RawGpioEdge", "mux", 20)]
    assert [r.value for r in records[:2]] == [0, 1]
    assert (records[2].edge, records[2].kernel_timestamp_ns) == (1, 123_456_789)
    port.close()


def test_a_look_at_the_clock_long_after_the_latest_edge_is_tapped_with_its_time(chip) -> None:
    """look_ns is now_ns; it is tapped (RawGpioClockRead) only once no edge has been read for
    CLOCK_READ_AFTER_NS, so a replay can judge where the live driver did (a lost or held-up signal)."""
    from u2sa_hw.ports.gpio.port import CLOCK_READ_AFTER_NS

    records: list = []
    port = open_gpio(device="mux", chip=chip.address, inputs=[20], tap=records.append)
    first = port.look_ns()   # no edge read yet: every look is worth its record
    assert [(type(r).__name__, r.device, r.clock_ns) for r in records] == [("RawGpioClockRead", "mux", first)]
    chip.drive(20, 1, time.monotonic_ns() - 10_000_000_000)   # an edge read long after it happened
    read_until(port, 1)
    records.clear()
    looked = port.look_ns()
    assert [(type(r).__name__, r.clock_ns) for r in records] == [("RawGpioClockRead", looked)]
    records.clear()
    fresh = time.monotonic_ns()
    chip.drive(20, 0, fresh)
    read_until(port, 1)
    records.clear()
    if port.look_ns() - fresh <= CLOCK_READ_AFTER_NS:   # (a machine that held this test up that long taps it)
        assert records == [], "a look just after an edge is carried by the edge's own stamp"
    port.close()


def test_a_tap_that_is_not_recording_gets_no_record_built(chip, monkeypatch: pytest.MonkeyPatch) -> None:
    from u2sa_hw.ports.gpio import port as gpio_port
    from u2sa_hw.ports.tap import RecordingTap

    def unwanted() -> None:
        raise AssertionError("a record was built while the tap was not recording")

    monkeypatch.setattr(gpio_port.m, "RawGpioEdge", unwanted)
    monkeypatch.setattr(gpio_port.m, "RawGpioWrite", unwanted)
    monkeypatch.setattr(gpio_port.m, "RawGpioClockRead", unwanted)
    records: list = []
    port = open_gpio(device="mux", chip=chip.address, inputs=[20], outputs={21: 0},
                     tap=RecordingTap(records.append, active=lambda: False))
    port.set(21, 1)
    chip.drive(20, 1, 5_000)
    assert [e.timestamp_ns for e in read_until(port, 1)] == [5_000] and records == []
    port.look_ns()   # long after that edge, yet no clock read is built either
    assert records == []
    port.close()


def test_a_line_in_use_is_refused_naming_its_consumer(chip) -> None:
    first = open_gpio(device="rc_input", chip=chip.address, inputs=[5, 6])
    with pytest.raises(PortUnavailable) as refused:
        open_gpio(device="other", chip=chip.address, inputs=[6], outputs={22: 0})
    assert "u2sa:rc_input" in str(refused.value) and "line 6" in str(refused.value)
    assert chip.read_output(22) == 0  # the refused request took nothing
    first.close()
    second = open_gpio(device="other", chip=chip.address, inputs=[6], outputs={22: 1})
    assert chip.read_output(22) == 1
    second.close()


def test_bad_arguments_are_refused_before_touching_the_chip(chip) -> None:
    with pytest.raises(ValueError, match="distinct"):
        open_gpio(device="x", chip=chip.address, inputs=[4], outputs={4: 0})
    with pytest.raises(ValueError, match="edge"):
        open_gpio(device="x", chip=chip.address, inputs=[4], edge="up")
    with pytest.raises(ValueError, match="at least one"):
        open_gpio(device="x", chip=chip.address)
    port = open_gpio(device="x", chip=chip.address, inputs=[4], outputs={7: 0})
    with pytest.raises(ValueError, match="not an output line"):
        port.set(4, 1)
    with pytest.raises(ValueError, match="0 or 1"):
        port.set(7, 2)
    with pytest.raises(ValueError, match="not a requested line"):
        port.get(9)
    port.close()


def test_a_closed_port_raises_port_closed_and_releases_its_lines(chip) -> None:
    port = open_gpio(device="x", chip=chip.address, inputs=[4])
    port.close()
    port.close()
    assert not port.is_open
    with pytest.raises(PortClosed):
        port.read_edges(0.01)
    open_gpio(device="y", chip=chip.address, inputs=[4]).close()


def test_losing_the_chip_raises_port_closed(chip) -> None:
    port = open_gpio(device="rc", chip=chip.address, inputs=[5])
    chip.vanish()
    with pytest.raises(PortClosed, match="rc"):
        wait_until(lambda: port.read_edges(0.05) and False, timeout=5.0, message="PortClosed")
    with pytest.raises(PortClosed):
        port.get(5)
    port.close()


def test_no_chip_at_a_mock_address_is_unavailable_with_the_fix(tmp_path: Path) -> None:
    with pytest.raises(PortUnavailable) as missing:
        open_gpio(device="rc", chip=f"mock:{tmp_path}/none.sock", inputs=[5])
    assert "none.sock" in str(missing.value) and "start the mock chip" in missing.value.fix


def test_a_missing_kernel_chip_is_unavailable_naming_it_and_the_fix() -> None:
    assert not os.path.exists("/dev/gpiochip0"), "this test describes a machine without GPIO"
    with pytest.raises(PortUnavailable) as missing:
        open_gpio(device="rc_input", chip="/dev/gpiochip0", inputs=[5, 6], outputs={21: 0})
    text = str(missing.value)
    assert "rc_input" in text and "/dev/gpiochip0 does not exist" in text
    assert "gpiodetect" in missing.value.fix and "mock:" in missing.value.fix


def test_a_file_that_is_not_a_gpio_chip_is_unavailable() -> None:
    with pytest.raises(PortUnavailable, match="not a GPIO character device"):
        open_gpio(device="rc_input", chip="/dev/null", inputs=[5])


def test_importing_the_port_does_not_import_gpiod() -> None:
    probe = "import sys, u2sa_hw.ports.gpio.port; print('gpiod' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert result.stdout.strip() == "False", result.stderr
