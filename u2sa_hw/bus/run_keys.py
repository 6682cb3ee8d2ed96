"""A process's own bus keys: a fresh bus key and pilot pair in a directory of its own.

What ``u2sa sim``, ``u2sa run`` without an installed key, a replay's private bus, a test session
and a bench script sign with (:func:`fresh_key_file`; :func:`use_run_key` for a tool run without
any key). The bus key is u2sa_hw.bus.key's, the pilot pair u2sa_hw.bus.pilot's.
"""

from __future__ import annotations

import atexit
import os
from pathlib import Path

from u2sa_hw.bus.key import KEY_ENV, SYSTEM_KEY, new_key, write_key
from u2sa_hw.bus.pilot import write_pilot_pair


def fresh_key_file(directory: Path | str) -> Path:
    """A new key in *directory*/bus.key (0600) and a new pilot pair beside it (u2sa_hw.bus.pilot):
    a simulation's, a test session's or ``u2sa run``'s own keys."""
    path = Path(directory) / "bus.key"
    write_key(path, new_key(), group=None)
    write_pilot_pair(path)
    return path


def use_run_key() -> Path | None:
    """For a tool run without a key (a bench script): a fresh key in $U2SA_BUS_KEY_FILE for this process and
    its children, removed at exit; its path, or None when a key was already set or installed."""
    if os.environ.get(KEY_ENV) or SYSTEM_KEY.exists():
        return None
    import shutil
    import tempfile
    directory = tempfile.mkdtemp(prefix="u2sa-run-key-")
    atexit.register(shutil.rmtree, directory, ignore_errors=True)
    path = fresh_key_file(directory)
    os.environ[KEY_ENV] = str(path)
    return path
