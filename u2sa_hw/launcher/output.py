"""The launcher's output: every child line prefixed with its service name.

Names are padded to one width and coloured when the stream is a terminal (and
``$NO_COLOR`` is unset), the way ``docker compose`` and ``honcho`` show several processes.
Children write bytes; partial lines are held until their newline (or the pipe's end).
"""

from __future__ import annotations

import os
import selectors
import subprocess
import sys
import threading
import time
from typing import IO, Callable, TextIO

LineSink = Callable[[str, str], None]
"""``sink(name, line)``: where the launcher sends each output line (without newline)."""

_PALETTE = (36, 33, 32, 35, 34, 96, 93, 92, 95, 94)
_LAUNCHER_STYLE = "1"   # bold
MAX_LINE = 64 * 1024


class PrefixedOutput:
    """Writes ``name | line`` to a text stream, colouring names on a terminal."""

    def __init__(self, stream: TextIO | None = None, *, names: list[str] = (), colour: bool | None = None,
                 launcher_name: str = "launcher") -> None:
        self.stream = stream or sys.stdout
        if colour is None:
            colour = hasattr(self.stream, "isatty") and self.stream.isatty() and not os.environ.get("NO_COLOR")
        self.colour = colour
        self.launcher_name = launcher_name
        self.width = max([len(n) for n in names] + [len(launcher_name)])
        self._styles: dict[str, str] = {launcher_name: _LAUNCHER_STYLE}
        for i, name in enumerate(names):
            self._styles.setdefault(name, str(_PALETTE[i % len(_PALETTE)]))
        self._lock = threading.Lock()

    def __call__(self, name: str, line: str) -> None:
        """Write one line for *name*."""
        label = name.ljust(self.width)
        if self.colour:
            style = self._styles.setdefault(name, str(_PALETTE[len(self._styles) % len(_PALETTE)]))
            label = f"\x1b[{style}m{label}\x1b[0m"
        with self._lock:
            try:
                self.stream.write(f"{label} | {line}\n")
                self.stream.flush()
            except (BrokenPipeError, ValueError):
                pass  # our own output went away (pager closed); the children keep running


class LineSplitter:
    """Turns the byte chunks of one child's pipe into whole lines for a sink."""

    def __init__(self, name: str, sink: LineSink) -> None:
        self.name = name
        self.sink = sink
        self._buffer = b""

    def feed(self, chunk: bytes) -> None:
        """Add bytes read from the pipe; emit every complete line."""
        self._buffer += chunk
        *lines, self._buffer = self._buffer.split(b"\n")
        for raw in lines:
            self._emit(raw)
        if len(self._buffer) > MAX_LINE:   # a child writing without newlines must not grow us forever
            self._emit(self._buffer)
            self._buffer = b""

    def close(self) -> None:
        """The pipe ended: emit what is left."""
        if self._buffer:
            self._emit(self._buffer)
            self._buffer = b""

    def _emit(self, raw: bytes) -> None:
        self.sink(self.name, raw.rstrip(b"\r").decode("utf-8", "replace"))


class ChildOutputs:
    """The children's output pipes, read on the launcher's loop thread and split into lines for *sink*."""

    def __init__(self, sink: LineSink) -> None:
        self.sink = sink
        self._pipes: dict[int, tuple[IO[bytes], LineSplitter]] = {}

    def __bool__(self) -> bool:
        return bool(self._pipes)

    def add(self, sel: selectors.BaseSelector, child: subprocess.Popen, name: str) -> None:
        """Read *child*'s stdout (non-blocking, through *sel*) as service *name*'s lines."""
        assert child.stdout is not None
        os.set_blocking(child.stdout.fileno(), False)
        self._pipes[child.stdout.fileno()] = (child.stdout, LineSplitter(name, self.sink))
        sel.register(child.stdout.fileno(), selectors.EVENT_READ, ("out", name))

    def read(self, sel: selectors.BaseSelector, fd: int) -> None:
        """Read what pipe *fd* holds; at its end, the last partial line goes out and the pipe is closed."""
        pipe, splitter = self._pipes[fd]
        try:
            chunk = os.read(fd, 65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            chunk = b""
        if chunk:
            splitter.feed(chunk)
            return
        sel.unregister(fd)
        del self._pipes[fd]
        splitter.close()
        pipe.close()

    def drain(self, sel: selectors.BaseSelector) -> None:
        """Read what the dead children left in their pipes (bounded, in case a grandchild holds one)."""
        deadline = time.monotonic() + 1.0
        while self._pipes and time.monotonic() < deadline:
            for key, _ in sel.select(0.1):
                if isinstance(key.data, tuple) and key.data[0] == "out":
                    self.read(sel, key.fd)
        for fd, (pipe, splitter) in list(self._pipes.items()):
            sel.unregister(fd)
            splitter.close()
            pipe.close()
        self._pipes.clear()
