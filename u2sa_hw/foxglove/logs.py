"""Service log lines as ``foxglove.Log`` messages.

Services do not publish their logs on the bus: each writes ``<log_dir>/<service>.log``
(``u2sa_hw.service.log``, one line per record: local ISO time with milliseconds, level,
service, thread id, message; a traceback continues on the lines after). The live bridge
tails those files (:class:`LogTail`); the export reads them whole (:func:`read_log_dir`).
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

from u2sa_hw.foxglove.wellknown import LOG_LEVELS, stamp

LINE = re.compile(r"^(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d)\.(\d{3}) (\w+)\s+(\S+) \[\d+\] (.*)$")


def parse_time(text: str, millis: str) -> int:
    """Nanoseconds since the epoch of a log line's local time stamp."""
    return int(time.mktime(time.strptime(text, "%Y-%m-%dT%H:%M:%S")) * 1_000_000_000) + int(millis) * 1_000_000


def log_message(t_ns: int, level: str, service: str, message: str, file: str) -> dict[str, Any]:
    """A foxglove.Log payload."""
    return {"timestamp": stamp(t_ns), "level": LOG_LEVELS.get(level.upper(), 0), "message": message,
            "name": service, "file": file, "line": 0}


def parse_lines(lines: Iterator[str], file: str) -> Iterator[tuple[int, dict[str, Any]]]:
    """``(time ns, Log)`` per record in *lines*; continuation lines join the record before them."""
    current: tuple[int, dict[str, Any]] | None = None
    for raw in lines:
        text = raw.rstrip("\n")
        m = LINE.match(text)
        if m is None:
            if current is not None and text:
                current[1]["message"] += "\n" + text
            continue
        if current is not None:
            yield current
        try:
            t_ns = parse_time(m.group(1), m.group(2))
        except ValueError:
            current = None
            continue
        current = (t_ns, log_message(t_ns, m.group(3), m.group(4), m.group(5), file))
    if current is not None:
        yield current


def read_log_dir(directory: Path, *, start_ns: int, end_ns: int) -> list[tuple[int, dict[str, Any]]]:
    """Every record of ``directory/*.log`` between *start_ns* and *end_ns*, in time order.

    A service's file grows across runs (it is appended to): the window keeps this run's lines.
    """
    out: list[tuple[int, dict[str, Any]]] = []
    for path in sorted(directory.glob("*.log")):
        try:
            with open(path, encoding="utf-8", errors="replace") as fh:
                out.extend(r for r in parse_lines(fh, path.name) if start_ns <= r[0] <= end_ns)
        except OSError:
            continue
    out.sort(key=lambda r: r[0])
    return out


@dataclass
class LogTail:
    """Follows every ``*.log`` in a directory from its current end; new files are picked up."""

    directory: Path
    _offsets: dict[Path, int] = field(default_factory=dict)
    _partial: dict[Path, str] = field(default_factory=dict)
    _started: bool = False

    def poll(self) -> list[tuple[int, dict[str, Any]]]:
        """Records written since the last call (the first call only notes where each file ends)."""
        out: list[tuple[int, dict[str, Any]]] = []
        try:
            paths = sorted(self.directory.glob("*.log"))
        except OSError:
            return out
        for path in paths:
            try:
                size = path.stat().st_size
            except OSError:
                continue
            if path not in self._offsets:
                self._offsets[path] = size if not self._started else 0
                continue
            offset = self._offsets[path]
            if size < offset:   # truncated or replaced: read it from the start
                offset = 0
            if size == offset:
                continue
            try:
                with open(path, "rb") as fh:
                    fh.seek(offset)
                    chunk = fh.read(size - offset)
            except OSError:
                continue
            self._offsets[path] = offset + len(chunk)
            text = self._partial.pop(path, "") + chunk.decode("utf-8", errors="replace")
            lines = text.split("\n")
            if lines[-1]:
                self._partial[path] = lines[-1]   # an incomplete last line waits for its end
            out.extend(parse_lines(iter(line for line in lines[:-1]), path.name))
        self._started = True
        out.sort(key=lambda r: r[0])
        return out
