"""ReconnectingPort: backoff without sleeping, loss accounting, and a real pty unplugged
and replugged under a serial port."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from conftest import wait_until
from u2sa_hw.ports import PortClosed, PortIOError, PortUnavailable, ReconnectingPort, open_serial


class FakeClock:
    """A monotonic clock the test moves by hand."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds


class Handle:
    """What a scripted opener hands out: something with close()."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.closed = False

    def close(self) -> None:
        self.closed = True


class ScriptedOpener:
    """Fails while ``down`` is set (like a missing device), else returns a new Handle."""

    def __init__(self, *, down: bool = False) -> None:
        self.down = down
        self.calls = 0
        self.opened: list[Handle] = []

    def __call__(self) -> Handle:
        self.calls += 1
        if self.down:
            raise PortUnavailable("gps", "cannot open", address="/dev/u2sa/gps", fix="plug it in")
        self.opened.append(Handle(self.calls))
        return self.opened[-1]


def backoff_waits(port: ReconnectingPort, clock: FakeClock, opener: ScriptedOpener, n: int) -> list[float]:
    """Let *n* open attempts fail, returning the wait the port asked for after each."""
    waits = []
    for _ in range(n):
        calls = opener.calls
        with pytest.raises(PortUnavailable):
            port.get()
        assert opener.calls == calls + 1
        waits.append(round(port.retry_in(), 6))
        clock.advance(port.retry_in())
    return waits


def test_opens_on_first_get_and_hands_out_the_same_port() -> None:
    opener = ScriptedOpener()
    port = ReconnectingPort(opener, device="gps", clock=FakeClock())
    assert port.state == "down" and port.port is None
    first = port.get()
    assert port.get() is first and port.state == "open"
    assert (opener.calls, port.attempts, port.reopen_attempts, port.losses) == (1, 1, 0, 0)


def test_failed_opens_back_off_doubling_to_the_cap_without_sleeping() -> None:
    clock, opener = FakeClock(), ScriptedOpener(down=True)
    port = ReconnectingPort(opener, device="gps", initial_backoff=0.1, max_backoff=1.0, clock=clock)
    assert backoff_waits(port, clock, opener, 6) == [0.1, 0.2, 0.4, 0.8, 1.0, 1.0]
    assert port.state == "down" and port.reopen_attempts == 5
    assert isinstance(port.last_error, PortUnavailable) and port.last_error.fix == "plug it in"


def test_get_inside_the_backoff_window_does_not_call_the_opener() -> None:
    clock, opener = FakeClock(), ScriptedOpener(down=True)
    port = ReconnectingPort(opener, device="gps", clock=clock)
    with pytest.raises(PortUnavailable):
        port.get()
    clock.advance(0.05)
    with pytest.raises(PortUnavailable) as info:
        port.get()
    assert opener.calls == 1
    assert "next attempt in 0.1 s" in str(info.value) and info.value.fix == "plug it in"
    opener.down = False
    clock.advance(0.06)
    assert isinstance(port.get(), Handle) and port.state == "open"


def test_lost_closes_the_port_and_reopens_after_the_backoff() -> None:
    clock, opener = FakeClock(), ScriptedOpener()
    port = ReconnectingPort(opener, device="gps", clock=clock)
    first = port.get()
    error = PortClosed("gps", "read failed, device lost", address="/dev/u2sa/gps", fix="replug")
    port.lost(error)
    assert first.closed and port.state == "down" and port.losses == 1 and port.last_error is error
    with pytest.raises(PortUnavailable):
        port.get()
    clock.advance(port.retry_in())
    second = port.get()
    assert second is not first and port.reopen_attempts == 1


def test_quick_deaths_keep_growing_the_wait_and_healthy_uptime_resets_it() -> None:
    clock, opener = FakeClock(), ScriptedOpener()
    port = ReconnectingPort(opener, device="gps", initial_backoff=0.1, max_backoff=5.0, healthy_after=10.0,
                            clock=clock)
    waits = []
    for _ in range(4):  # opens, dies at once
        port.get()
        port.lost(PortClosed("gps", "lost"))
        waits.append(round(port.retry_in(), 6))
        clock.advance(port.retry_in())
    assert waits == [0.1, 0.2, 0.4, 0.8]
    port.get()
    clock.advance(60.0)  # a healthy hour, in short
    port.lost(PortIOError("gps", "EIO"))
    assert round(port.retry_in(), 6) == 0.1


def test_a_report_about_a_replaced_port_is_ignored() -> None:
    clock, opener = FakeClock(), ScriptedOpener()
    port = ReconnectingPort(opener, device="gps", clock=clock)
    old = port.get()
    port.lost(PortClosed("gps", "lost"), port=old)
    clock.advance(1.0)
    new = port.get()
    port.lost(PortClosed("gps", "lost again"), port=old)  # the writer thread, late
    assert port.state == "open" and port.port is new and port.losses == 1 and not new.closed


def test_call_marks_the_port_lost_on_port_errors_and_re_raises() -> None:
    clock, opener = FakeClock(), ScriptedOpener()
    port = ReconnectingPort(opener, device="gps", clock=clock)
    assert port.call(lambda h: h.n) == 1

    def fails(handle: Handle) -> None:
        raise PortIOError("gps", "EIO")

    with pytest.raises(PortIOError):
        port.call(fails)
    assert port.state == "down" and port.losses == 1 and opener.opened[0].closed


def test_other_opener_failures_are_wrapped_or_propagate() -> None:
    def closes_during_handshake() -> Handle:
        raise PortClosed("imu", "closed during the handshake", fix="check the cable")

    port = ReconnectingPort(closes_during_handshake, device="imu", clock=FakeClock())
    with pytest.raises(PortUnavailable) as info:
        port.get()
    assert isinstance(info.value.__cause__, PortClosed) and info.value.fix == "check the cable"

    def buggy() -> Handle:
        raise TypeError("a bug, not a device problem")

    with pytest.raises(TypeError):
        ReconnectingPort(buggy, device="imu", clock=FakeClock()).get()


def test_close_is_final() -> None:
    opener = ScriptedOpener()
    port = ReconnectingPort(opener, device="gps", clock=FakeClock())
    handle = port.get()
    port.close()
    port.close()
    assert handle.closed and port.state == "closed"
    with pytest.raises(PortClosed):
        port.get()


def test_bad_backoff_settings_are_refused() -> None:
    with pytest.raises(ValueError, match="gps"):
        ReconnectingPort(ScriptedOpener(), device="gps", initial_backoff=2.0, max_backoff=1.0)


class MockGpsPty:
    """A mock device's end of a pty, published at a fixed symlink like a udev name."""

    def __init__(self, link: Path) -> None:
        self.link = link
        self.master = -1

    def plug(self) -> None:
        self.master, slave = os.openpty()
        os.symlink(os.ttyname(slave), self.link)
        os.close(slave)

    def unplug(self) -> None:
        os.close(self.master)
        self.master = -1
        self.link.unlink()


def test_a_serial_device_unplugged_and_replugged_is_reopened(tmp_path: Path) -> None:
    clock = FakeClock()
    mock = MockGpsPty(tmp_path / "gps")
    mock.plug()
    port = ReconnectingPort(lambda: open_serial(str(mock.link), device="gps", timeout=0.05),
                            device="gps", clock=clock)
    try:
        port.get()  # pyserial flushes input on open: the device talks once the port is open
        os.write(mock.master, b"$GPGGA,1*00\r\n")
        assert wait_until(lambda: port.call(lambda p: p.readline())) == b"$GPGGA,1*00\r\n"

        mock.unplug()
        with pytest.raises(PortClosed):
            wait_until(lambda: port.call(lambda p: p.read(16)), timeout=5.0)
        assert port.state == "down" and port.losses == 1

        clock.advance(port.retry_in())
        with pytest.raises(PortUnavailable) as info:  # still unplugged: the link is gone
            port.get()
        assert "does not exist" in info.value.fix

        mock.plug()
        clock.advance(port.retry_in())
        port.get()
        os.write(mock.master, b"$GPGGA,2*00\r\n")
        assert wait_until(lambda: port.call(lambda p: p.readline())) == b"$GPGGA,2*00\r\n"
        assert port.state == "open" and port.reopen_attempts == 2
    finally:
        port.close()
        if mock.master >= 0:
            os.close(mock.master)
