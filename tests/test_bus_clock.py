"""The saved signing time: a board without an RTC refuses replays from before its reboot (docs/security.md).

Injected clocks throughout: the wall clock (``BusAuth(wall_us=...)``), the boot identity and
``CLOCK_BOOTTIME`` (``ClockStore(boot_id=..., boottime_us=...)``) and the monotonic clock
that paces the saves. One test opens a real transport with ``$STATE_DIRECTORY``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from conftest import unprivileged

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.auth import OK, REPLAYED, WINDOW_US, BusAuth, Keyring
from u2sa_hw.bus.clock import FILE_NAME, SAVE_EVERY_S, STATE_ENV, ClockStore, store_from_env
from u2sa_hw.bus.key import new_key, write_key

DAY_US = 86_400_000_000
YESTERDAY = 1_790_000_000_000_000          # µs since 1970: November 2026
BOOTED_IN_1970 = 5_000_000                 # a board without an RTC, 5 s after boot


@pytest.fixture
def ring(tmp_path: Path) -> Keyring:
    write_key(tmp_path / "bus.key", new_key(), group=None)
    return Keyring(tmp_path / "bus.key")


class Clocks:
    """The boot id, CLOCK_BOOTTIME and the monotonic clock of one board, set by the test."""

    def __init__(self) -> None:
        self.boot, self.boottime_us, self.mono = "boot-1", 0, 0.0

    def store(self, directory: Path) -> ClockStore:
        return ClockStore(directory, monotonic=lambda: self.mono, boottime_us=lambda: self.boottime_us,
                          boot_id=lambda: self.boot)


def stop_packet(auth: BusAuth) -> bytes:
    stop = t.StopCommand()
    stop.all = True
    return auth.sign(ch.STOP, stop.encode())


def test_a_packet_captured_before_a_reboot_is_refused_by_a_board_whose_clock_reads_1970(ring: Keyring,
                                                                                      tmp_path: Path) -> None:
    clocks = Clocks()
    captured = stop_packet(BusAuth(ring, wall_us=lambda: YESTERDAY))          # on the wire yesterday
    board = BusAuth(ring, wall_us=lambda: YESTERDAY + 3_600_000_000)          # the board ran an hour after it
    clocks.store(tmp_path).save(board.high_water())

    # Without the saved time (the bug): the day-old stop verifies on the rebooted board.
    assert BusAuth(ring, wall_us=lambda: BOOTED_IN_1970).verify(ch.STOP, captured) == OK

    clocks.boot, clocks.boottime_us = "boot-2", 5_000_000                     # rebooted, clock in 1970 again
    rebooted = BusAuth(ring, wall_us=lambda: BOOTED_IN_1970)
    start = clocks.store(tmp_path).start_at(WINDOW_US)
    assert start == YESTERDAY + 3_600_000_000 + WINDOW_US                     # the window starts at the saved time
    assert rebooted.adopt(start)
    assert rebooted.verify(ch.STOP, captured) == REPLAYED
    # ... and a sender signing after the saved time (the vehicle, live) is heard at once.
    live = stop_packet(BusAuth(ring, wall_us=lambda: YESTERDAY + 3_600_000_000 + 30_000_000))
    assert rebooted.verify(ch.STOP, live) == OK


def test_after_a_restart_in_the_same_boot_the_clock_resumes_without_drifting_ahead(ring: Keyring,
                                                                                 tmp_path: Path) -> None:
    clocks = Clocks()
    clocks.boottime_us = 100_000_000
    clocks.store(tmp_path).save(YESTERDAY)
    clocks.boottime_us += 7_000_000                      # a service restarted 7 s later, same boot
    start = clocks.store(tmp_path).start_at(WINDOW_US)
    assert start == YESTERDAY + 7_000_000                # what an RTC would read: not 20 s ahead
    restarted = BusAuth(ring, wall_us=lambda: BOOTED_IN_1970 + 107_000_000)
    assert restarted.adopt(start) and restarted.now() == start
    day_old = stop_packet(BusAuth(ring, wall_us=lambda: YESTERDAY - DAY_US))
    assert restarted.verify(ch.STOP, day_old) == REPLAYED
    # a board whose clock is ahead of the saved time keeps it: the clock never goes back
    ahead = BusAuth(ring, wall_us=lambda: YESTERDAY + DAY_US)
    assert not ahead.adopt(start) and ahead.now() == YESTERDAY + DAY_US


def test_saves_are_paced_atomic_and_never_lower_the_boards_time(tmp_path: Path) -> None:
    clocks = Clocks()
    store = clocks.store(tmp_path)
    assert not store.due()
    clocks.mono = SAVE_EVERY_S - 0.1
    assert not store.due()
    clocks.mono = SAVE_EVERY_S
    assert store.due()
    assert store.save(YESTERDAY) and not store.due()
    other = clocks.store(tmp_path)                        # another service of the board, its clock behind
    assert other.save(YESTERDAY - 60_000_000)
    saved = json.loads((tmp_path / FILE_NAME).read_text())
    assert saved == {"signing_us": YESTERDAY, "boot_id": "boot-1", "boottime_us": 0}
    assert [p.name for p in tmp_path.iterdir()] == [FILE_NAME]   # no temp file left behind
    assert other.start_at(WINDOW_US) == YESTERDAY


def test_out_of_range_saved_times_are_ignored_and_bad_files_only_logged(ring: Keyring, tmp_path: Path,
                                                                        caplog: pytest.LogCaptureFixture) -> None:
    now = YESTERDAY
    sane = BusAuth(ring, wall_us=lambda: now)
    assert not sane.adopt(now + 2 * 366 * DAY_US), "two years ahead of a clock that is set"
    assert not sane.adopt(2 ** 60)
    assert sane.now() == now
    (tmp_path / FILE_NAME).write_text("{not json")
    store = Clocks().store(tmp_path)
    assert store.start_at(WINDOW_US) is None and store.start_at(WINDOW_US) is None
    assert caplog.text.count("cannot read the saved bus clock") == 1
    assert Clocks().store(tmp_path / "none").start_at(WINDOW_US) is None     # never saved: nothing, no noise


def test_the_store_comes_from_state_directory_and_a_missing_one_is_no_store(tmp_path: Path) -> None:
    assert store_from_env({}) is None
    assert store_from_env({STATE_ENV: ""}) is None
    store = store_from_env({STATE_ENV: f"{tmp_path}/a:{tmp_path}/b"})   # systemd joins several with ':'
    assert store is not None and store.path == tmp_path / "a" / FILE_NAME


def test_a_directory_that_cannot_be_written_keeps_the_service_working() -> None:
    import shutil
    import subprocess
    import sys
    import tempfile

    shared = Path(tempfile.mkdtemp(prefix="u2sa-clock-", dir="/tmp"))
    try:
        shared.chmod(0o755)
        locked = shared / "locked"
        locked.mkdir()
        locked.chmod(0o555)   # readable, not writable (by the user nobody; root ignores modes), whatever the umask
        code = ("from u2sa_hw.bus.clock import ClockStore\n"
                f"s = ClockStore({str(locked)!r})\nprint(s.save(1), s.save(2), s.start_at(5))\n")
        done = subprocess.run(unprivileged([sys.executable, "-c", code]), capture_output=True, text=True, timeout=60)
    finally:
        shutil.rmtree(shared, ignore_errors=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["False", "False", "None"]
    assert done.stderr.count("cannot save the bus clock") == 1


def test_a_transport_starts_from_the_saved_time_and_saves_when_it_stops(tmp_path: Path, lcm_url: str,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    from u2sa_hw.bus.transport import Transport

    later = time.time_ns() // 1000 + 100 * DAY_US         # saved by a vehicle whose clock ran 100 days ahead
    (tmp_path / FILE_NAME).write_text(json.dumps({"signing_us": later, "boot_id": "another boot", "boottime_us": 0}))
    monkeypatch.setenv(STATE_ENV, str(tmp_path))
    transport = Transport(lcm_url, name="clock-test")
    assert transport.auth is not None and transport.auth.now() >= later + WINDOW_US
    transport.stop()
    saved = json.loads((tmp_path / FILE_NAME).read_text())
    assert saved["signing_us"] >= later + WINDOW_US and saved["boot_id"] != "another boot"
    monkeypatch.delenv(STATE_ENV)
    plain = Transport(lcm_url, name="clock-test-cli")      # a u2sa command: no state directory, no saved time
    assert plain.auth is not None and plain.auth.now() < later
    plain.stop()
