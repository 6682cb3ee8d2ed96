"""A pty at a symlink: the serial wire end a mock or replay device holds (the one pty implementation).

:class:`PtyLink` opens a pty pair, puts the slave in raw mode and the master in non-blocking
mode, and points a symlink (``/tmp/sim/gps``, ``<run>/dev/gps``) at the slave (``/dev/pts/N``),
so a driver opens the symlink with pyserial exactly as it would open ``/dev/u2sa/gps``
(``mock+serial://`` addresses). A reader thread hands each chunk the driver writes to
``on_data``. The link holds its own slave descriptor, so the master never sees EIO while no
driver has the port open; bytes written then wait in the kernel buffer.

Both device families use it: the mock sensors (``u2sa_hw.mocks.pty_serial.PtySerialDevice``:
faults, unplug and replug, history) and the replay's serial device
(``u2sa_hw.ports.serial.replay.ReplaySerialDevice``: recorded bytes with backpressure). The
symlink is made atomically (a temporary link renamed over it), so a driver never sees the path
missing while a device is replugged, and removed at close only while it still points at this
link's slave.
"""

from __future__ import annotations

import array
import errno
import fcntl
import logging
import os
import select
import termios
import threading
import tty
from pathlib import Path
from typing import Callable

log = logging.getLogger(__name__)

READ_SIZE = 4096   # bytes the reader takes from the master at once


class PtyLink:
    """One plugged-in lifetime of a pty at *link_path*; *on_data* gets what the driver writes.

    ``open()`` creates the pty, the symlink and the reader; ``close()`` undoes them (and may be
    called from *on_data*). *name* is the device's name, in errors, logs and the thread's name.
    """

    def __init__(self, *, link_path: str | os.PathLike[str], name: str,
                 on_data: Callable[[bytes], None] | None = None) -> None:
        self.link_path = Path(link_path)
        self.name = name
        self.on_data = on_data
        self.master = self.slave = -1
        self.slave_name = ""
        self._wake_r = self._wake_w = -1
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def is_open(self) -> bool:
        """True between ``open()`` and ``close()``."""
        return self.master >= 0

    def open(self) -> None:
        """Create the pty (raw slave, non-blocking master), point the symlink at it and start the reader.

        OSError names the device and the link when the symlink cannot be made (choose a writable path).
        """
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        flags = fcntl.fcntl(self.master, fcntl.F_GETFL)
        fcntl.fcntl(self.master, fcntl.F_SETFL, flags | os.O_NONBLOCK)
        self.slave_name = os.ttyname(self.slave)
        self._wake_r, self._wake_w = os.pipe()
        self._closing.clear()
        try:
            self.link_path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.link_path.with_name(f".{self.link_path.name}.{os.getpid()}.{threading.get_ident()}")
            if tmp.is_symlink():
                tmp.unlink()
            os.symlink(self.slave_name, tmp)
            os.replace(tmp, self.link_path)   # atomic: a driver never sees the path missing mid-replug
        except OSError as exc:
            self._close_fds()
            raise OSError(exc.errno, f"{self.name}: cannot create the device link {self.link_path}: "
                                     f"{exc.strerror}; choose a writable link_path") from exc
        self._thread = threading.Thread(target=self._read_loop, daemon=True, name=f"pty-{self.name}")
        self._thread.start()

    def close(self) -> None:
        """Stop the reader, remove the symlink (while it is still ours) and close the pty."""
        if not self.is_open:
            return
        self._closing.set()
        try:
            os.write(self._wake_w, b"x")
        except OSError:
            pass
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():   # on_data may close the link
            thread.join(timeout=5.0)
        try:
            if os.readlink(self.link_path) == self.slave_name:
                self.link_path.unlink()
        except OSError:
            pass   # already gone, or replaced by someone else: leave it
        self._close_fds()

    def _close_fds(self) -> None:
        for fd in (self.master, self.slave, self._wake_r, self._wake_w):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self.slave = self._wake_r = self._wake_w = -1

    def write(self, data: bytes | memoryview) -> int:
        """Write what the master takes now (non-blocking); the bytes accepted (0 when the buffer is full).

        OSError (EIO: the pty went away) is the caller's to handle.
        """
        try:
            return os.write(self.master, data)
        except BlockingIOError:
            return 0

    def wait_writable(self, timeout_s: float) -> None:
        """Wait up to *timeout_s* for room in the master's buffer."""
        select.select([], [self.master], [], timeout_s)

    def pending(self) -> int:
        """Bytes written into the pty that the driver has not read yet (0 when closed)."""
        if self.slave < 0:
            return 0
        buf = array.array("i", [0])
        try:
            fcntl.ioctl(self.slave, termios.FIONREAD, buf, True)
        except OSError:
            return 0
        return buf[0]

    def termios_attrs(self) -> list:
        """The line settings the driver applied through its end (the master shares the slave's termios)."""
        return termios.tcgetattr(self.master)

    def _read_loop(self) -> None:
        master, wake = self.master, self._wake_r
        while not self._closing.is_set():
            try:
                ready, _, _ = select.select([master, wake], [], [])
            except (OSError, ValueError):
                return
            if wake in ready or master not in ready:
                continue
            try:
                data = os.read(master, READ_SIZE)
            except BlockingIOError:
                continue
            except OSError as exc:
                if exc.errno != errno.EIO:
                    log.warning("%s: read from %s failed: %s", self.name, self.slave_name, exc)
                return
            if not data:
                return
            if self.on_data is not None:
                try:
                    self.on_data(data)
                except Exception:   # a device model's bug must not kill the link
                    log.exception("%s: handler failed on %r", self.name, data[:64])
