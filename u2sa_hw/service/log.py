"""Logger (requirement C3): one file per service plus stderr (for journald).

Each line: ISO timestamp, level, service name, thread id, message. The file handler
flushes on every record. Levels: debug, info, warn, error.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

LEVELS = {"debug": logging.DEBUG, "info": logging.INFO, "warn": logging.WARNING,
          "warning": logging.WARNING, "error": logging.ERROR}
LEVEL_NAMES = tuple(LEVELS)


def level_number(level: str) -> int:
    """The logging level of *level* (debug, info, warn/warning, error; any case); ValueError names them."""
    try:
        return LEVELS[level.strip().lower()]
    except KeyError:
        raise ValueError(f"unknown log level {level!r}; use one of {', '.join(LEVEL_NAMES)}") from None


def set_level(level: str) -> None:
    """Set the process's (root logger's) level to *level*; ValueError for an unknown name."""
    logging.getLogger().setLevel(level_number(level))
FORMAT = "%(asctime)s.%(msecs)03d %(levelname)-5s %(service)s [%(thread)d] %(message)s"
DATEFMT = "%Y-%m-%dT%H:%M:%S"


class _ServiceFilter(logging.Filter):
    def __init__(self, service: str) -> None:
        super().__init__()
        self.service = service

    def filter(self, record: logging.LogRecord) -> bool:
        record.service = self.service
        if record.levelname == "WARNING":
            record.levelname = "WARN"
        return True


def setup_service_logging(service: str, *, log_dir: Path | str | None, level: str = "info",
                          stderr: bool = True) -> logging.Logger:
    """Configure the root logger for a service process; return the service's logger.

    Raises ValueError for an unknown level and OSError (with the path) when the log
    directory cannot be created.
    """
    lvl = level_number(level)
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.setLevel(lvl)
    fmt = logging.Formatter(FORMAT, DATEFMT)
    filt = _ServiceFilter(service)
    if log_dir is not None:
        path = Path(log_dir)
        path.mkdir(parents=True, exist_ok=True)
        fh = logging.FileHandler(path / f"{service}.log", encoding="utf-8")  # flushes per record
        fh.setFormatter(fmt)
        fh.addFilter(filt)
        root.addHandler(fh)
    if stderr:
        sh = logging.StreamHandler(sys.stderr)
        sh.setFormatter(fmt)
        sh.addFilter(filt)
        root.addHandler(sh)
    return logging.getLogger(f"u2sa.{service}")
