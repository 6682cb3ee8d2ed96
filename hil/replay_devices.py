"""Mock devices that play recorded raw I/O back to the real drivers.

Each device stands at the address the replay writes into its driver's config and is fed
the recorded ``RAW.<device>`` records by the player (hil/player.py):

- :class:`ReplaySerialDevice`: a pty at a symlink (like ``mock_devices.pty_serial``);
  recorded RX bytes are written into it, with backpressure instead of drops; what the
  driver writes is kept and checked against the recorded TX bytes.
- CAN and I2C replay devices live in :mod:`hil.replay_buses`, GPIO and PWM in
  :mod:`hil.replay_gpio`.

Every device has ``config_changes()`` (the config fields that point its driver at it),
``start()``/``stop()``, ``ready(pid, health)`` (the driver has opened its side), ``feed(record)``,
``pending()`` (input the driver has not taken yet: the pacing of ``--fast``) and
``report()`` (counts and divergences for the summary).
"""

from __future__ import annotations

import array
import fcntl
import os
import select
import termios
import threading
import time
import tty
from pathlib import Path
from typing import Any, Protocol

from u2sa_hw.ports.address import DeviceAddress, make_address
from u2sa_hw.ports.tap import RX, TX


class ReplayStalled(RuntimeError):
    """A driver stopped taking its recorded input; the message names the device."""


class ReplayDevice(Protocol):
    """What the player and the orchestration need from a replay device."""

    name: str
    kind: str

    def mock_address(self, real: DeviceAddress | None) -> str:
        """The ``mock+`` address the driver opens instead of the recorded *real* one (same kind)."""

    def config_changes(self) -> dict[str, Any]:
        """Config fields the replay needs changed besides the address (e.g. a faster rate)."""

    def start(self) -> None:
        """Open the device (before the driver starts)."""

    def stop(self) -> None:
        """Close it."""

    def ready(self, pid: int | None, health: dict[str, str]) -> bool:
        """True once the driver (process *pid*, whose latest health details are *health*) has opened its side."""

    def feed(self, record: Any) -> None:
        """Play one recorded record (RX) or note one the driver should send (TX)."""

    def pending(self) -> int:
        """Input fed but not yet taken by the driver."""

    def report(self) -> dict[str, Any]:
        """Counts and divergences."""


def fd_open_by(pid: int | None, target: str) -> bool:
    """True when process *pid* has a descriptor open on the path *target* (Linux /proc)."""
    if not pid:
        return False
    fd_dir = Path(f"/proc/{pid}/fd")
    try:
        entries = list(fd_dir.iterdir())
    except OSError:
        return False
    for entry in entries:
        try:
            if os.readlink(entry) == target:
                return True
        except OSError:
            continue
    return False


class ReplaySerialDevice:
    """A pty at *link_path*; recorded RX bytes go to the driver, its writes are compared with TX."""

    kind = "serial"

    def __init__(self, *, name: str, link_path: Path | str, burst_gap_s: float = 0.05,
                 write_timeout_s: float = 10.0) -> None:
        self.name = name
        self.burst_gap_s = burst_gap_s  # records closer than this are one burst (the driver's epoch_gap_s)
        self.link_path = Path(link_path)
        self.write_timeout_s = write_timeout_s
        self._master = self._slave = -1
        self.slave_name = ""
        self._stop = threading.Event()
        self._reader: threading.Thread | None = None
        self._written = bytearray()        # what the driver wrote
        self._expected_tx = bytearray()    # what the recorded driver wrote
        self.fed_bytes = 0
        self.fed_chunks = 0

    @property
    def address(self) -> str:
        """The path the driver opens."""
        return str(self.link_path)

    def mock_address(self, real: DeviceAddress | None) -> str:
        """``mock+serial://<the pty symlink>`` with the recorded address's framing."""
        params = {k: v for k, v in real.params.items() if k not in ("usb", "serial")} if real is not None else {}
        return make_address("serial", self.address, params=params, mock=True, device=self.name).url

    def config_changes(self) -> dict[str, Any]:
        """Nothing besides the address."""
        return {}

    def start(self) -> None:
        """Create the pty (raw mode, non-blocking master), the symlink and the reader of driver writes."""
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        flags = fcntl.fcntl(self._master, fcntl.F_GETFL)
        fcntl.fcntl(self._master, fcntl.F_SETFL, flags | os.O_NONBLOCK)
        self.slave_name = os.ttyname(self._slave)
        self.link_path.parent.mkdir(parents=True, exist_ok=True)
        if self.link_path.is_symlink():
            self.link_path.unlink()
        os.symlink(self.slave_name, self.link_path)
        self._reader = threading.Thread(target=self._read_loop, name=f"replay-{self.name}", daemon=True)
        self._reader.start()

    def stop(self) -> None:
        """Stop the reader, remove the symlink, close the pty."""
        self._stop.set()
        if self._reader is not None:
            self._reader.join(timeout=2.0)
            self._reader = None
        try:
            if self.link_path.is_symlink():
                self.link_path.unlink()
        except OSError:
            pass
        for fd in (self._master, self._slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = -1

    def ready(self, pid: int | None, health: dict[str, str]) -> bool:
        """The driver has finished opening the pty: pyserial flushes the input while it opens, so
        bytes fed earlier would be lost. A serial sensor says ``port = open`` in its health once
        the open returned; for a driver without that detail, holding the slave open must do."""
        if "port" in health:
            return health["port"] == "open" and fd_open_by(pid, self.slave_name)
        return fd_open_by(pid, self.slave_name)

    def feed(self, record: Any) -> None:
        """Write an RX record's bytes into the pty (waiting while the driver's buffer is full); note TX."""
        data = bytes(record.data)
        if record.direction == TX:
            self._expected_tx += data
            return
        if record.direction != RX or not data:
            return
        view = memoryview(data)
        deadline = time.monotonic() + self.write_timeout_s
        while view:
            try:
                n = os.write(self._master, view)
                view = view[n:]
                continue
            except BlockingIOError:
                pass
            if time.monotonic() > deadline:
                raise ReplayStalled(f"{self.name}: the driver has not read its serial input for "
                                    f"{self.write_timeout_s:g} s ({self.address}); is the service still running?")
            select.select([], [self._master], [], 0.05)
        self.fed_bytes += len(data)
        self.fed_chunks += 1

    @staticmethod
    def merge(first: Any, second: Any, *, limit: int = 4096) -> Any | None:
        """One RX record holding both chunks (``--fast`` feeds runs at once), or None when they cannot merge."""
        if first.direction != RX or second.direction != RX or first.length + second.length > limit:
            return None
        merged = type(first)()
        merged.device, merged.direction = first.device, RX
        merged.data = bytes(first.data) + bytes(second.data)
        merged.length = len(merged.data)
        return merged

    def pending(self) -> int:
        """Bytes in the pty the driver has not read yet."""
        if self._slave < 0:
            return 0
        buf = array.array("i", [0])
        try:
            fcntl.ioctl(self._slave, termios.FIONREAD, buf, True)
        except OSError:
            return 0
        return buf[0]

    def _read_loop(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master], [], [], 0.1)
                if ready:
                    self._written += os.read(self._master, 4096)
            except BlockingIOError:
                continue
            except (OSError, ValueError):
                return

    def report(self) -> dict[str, Any]:
        """Bytes and chunks fed; the driver's writes against the recorded ones."""
        written, expected = bytes(self._written), bytes(self._expected_tx)
        out: dict[str, Any] = {"kind": self.kind, "fed_bytes": self.fed_bytes, "fed_chunks": self.fed_chunks,
                               "tx_bytes": len(written), "tx_recorded_bytes": len(expected)}
        if written != expected:
            common = next((i for i, (a, b) in enumerate(zip(written, expected)) if a != b), min(len(written),
                                                                                          len(expected)))
            out["divergences"] = 1
            out["divergence"] = (f"the driver wrote {len(written)} bytes, the recording has {len(expected)}; "
                                 f"they differ from byte {common}")
        else:
            out["divergences"] = 0
        return out
