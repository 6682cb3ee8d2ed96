"""The signing clock kept across restarts: no replay window below what the vehicle already saw.

A receiver refuses a new sender's first packet when it is older than the window
(``bus_auth.WINDOW_US``) on its signing clock. A board without a real-time clock boots in
1970, or where fake-hwclock last saved it: until it hears live traffic its window is in the
past, and a packet captured a day earlier would verify. So every transport of a service
saves the highest signing time it reached (its signing clock: the wall clock moved forward to
every verified and sent counter) in ``$STATE_DIRECTORY/bus-clock`` (systemd's state
directory, ``/var/lib/u2sa`` for the units; ``u2sa run`` gives its children the profile's
``data_dir``), at most every :data:`SAVE_EVERY_S` and when it stops, atomically (temp file,
fsync, rename), never lowering what another service of the board saved.

A transport that opens reads it and starts its signing clock no lower than:

* after a restart within the same boot (same ``/proc/sys/kernel/random/boot_id``): the saved
  time plus the time elapsed since it was saved (``CLOCK_BOOTTIME``), which is as good as a
  real-time clock, so the window is where an RTC would put it and nothing drifts ahead;
* after a reboot, when the elapsed time is unknown: the saved time plus the window, so the
  window starts at the saved time: nothing signed before it is accepted from a new sender.

A process without ``$STATE_DIRECTORY`` (the ``u2sa`` commands, a service started by hand) or
whose directory cannot be written keeps working without it (said once in the log).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
import time
from pathlib import Path
from typing import Callable

log = logging.getLogger("u2sa_hw.bus.clock")

STATE_ENV = "STATE_DIRECTORY"     # systemd's StateDirectory= (colon-separated when several); the launcher sets it
FILE_NAME = "bus-clock"
SAVE_EVERY_S = 60.0
BOOT_ID_FILE = "/proc/sys/kernel/random/boot_id"


def _boottime_us() -> int:
    return time.clock_gettime_ns(time.CLOCK_BOOTTIME) // 1000


def _boot_id() -> str:
    try:
        return Path(BOOT_ID_FILE).read_text().strip()
    except OSError:
        return ""


class ClockStore:
    """The board's saved signing time in *directory*/bus-clock (see the module docstring).

    *monotonic*, *boottime_us* and *boot_id* are the clocks and the boot identity; tests give
    their own.
    """

    def __init__(self, directory: Path | str, *, monotonic: Callable[[], float] = time.monotonic,
                 boottime_us: Callable[[], int] = _boottime_us, boot_id: Callable[[], str] = _boot_id,
                 every_s: float = SAVE_EVERY_S) -> None:
        self.path = Path(directory) / FILE_NAME
        self._monotonic = monotonic
        self._boottime_us = boottime_us
        self._boot_id = boot_id
        self._every_s = every_s
        self._next_save = monotonic() + every_s
        self._lock = threading.Lock()
        self._error_logged = False

    def _read(self) -> tuple[int, str, int] | None:
        """(signing µs, boot id, boottime µs) as saved, or None (missing or unreadable: said once)."""
        try:
            data = json.loads(self.path.read_text())
            return int(data["signing_us"]), str(data["boot_id"]), int(data["boottime_us"])
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, TypeError) as exc:
            self._log_once(f"cannot read the saved bus clock {self.path} ({exc}); starting without it "
                           "(it is rewritten within a minute)")
            return None

    def _projected(self, saved: tuple[int, str, int]) -> int:
        """The saved signing time carried to now: plus the time elapsed in the same boot; as saved after a reboot."""
        signing_us, boot, boottime_us = saved
        if boot and boot == self._boot_id():
            return signing_us + max(0, self._boottime_us() - boottime_us)
        return signing_us

    def start_at(self, window_us: int) -> int | None:
        """The lowest signing clock a transport opening now may start from (µs), or None without a saved time.

        Same boot: the saved time plus the time since (an RTC's reading). After a reboot: the
        saved time plus *window_us*, so the receive window starts no lower than the saved time.
        """
        saved = self._read()
        if saved is None:
            return None
        same_boot = bool(saved[1]) and saved[1] == self._boot_id()
        return self._projected(saved) if same_boot else saved[0] + window_us

    def due(self) -> bool:
        """True when :data:`SAVE_EVERY_S` passed since the last save (cheap: one clock read)."""
        return self._monotonic() >= self._next_save

    def save(self, signing_us: int) -> bool:
        """Store *signing_us* (or what another process saved, carried to now, when that is higher); False on error."""
        with self._lock:
            self._next_save = self._monotonic() + self._every_s
            saved = self._read()
            value = max(signing_us, self._projected(saved)) if saved else signing_us
            text = json.dumps({"signing_us": value, "boot_id": self._boot_id(), "boottime_us": self._boottime_us()})
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                import tempfile   # imported where written: most processes never write the store
                fd, tmp = tempfile.mkstemp(dir=self.path.parent, prefix=f".{FILE_NAME}.")
            except OSError as exc:
                self._log_once(f"cannot save the bus clock in {self.path.parent} ({exc.strerror or exc}); a reboot "
                               "without a real-time clock then accepts older replays (docs/security.md)")
                return False
            try:
                with os.fdopen(fd, "w") as f:
                    f.write(text + "\n")
                    f.flush()
                    os.fsync(f.fileno())
                os.replace(tmp, self.path)
            except OSError as exc:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
                self._log_once(f"cannot save the bus clock {self.path} ({exc.strerror or exc})")
                return False
            return True

    def _log_once(self, text: str) -> None:
        if not self._error_logged:
            self._error_logged = True
            log.warning("%s", text)


def store_from_env(env: dict[str, str] | None = None) -> ClockStore | None:
    """The store in ``$STATE_DIRECTORY`` (its first path), or None when the process has none."""
    value = (os.environ if env is None else env).get(STATE_ENV, "")
    first = value.split(":", 1)[0].strip()
    return ClockStore(first) if first else None
