"""Kernel names for a process's own threads (the bus's receive thread, a service's loop).

In the bus layer because the transport names its LCM thread; the service contract names its
loop with the same call.
"""

from __future__ import annotations

from typing import Any


def name_native_thread(thread: Any, label: str) -> None:
    """Give *thread* (a started ``threading.Thread`` of this process) *label* as its kernel name.

    ``top -H``, ``ps -L`` and bench/stack.py then tell a service's bus handler from its own
    loop; the kernel keeps 15 bytes. Best effort: a thread that is gone, or no /proc, is skipped.
    """
    tid = getattr(thread, "native_id", None)
    if tid is None:
        return
    try:
        with open(f"/proc/self/task/{tid}/comm", "w", encoding="ascii", errors="replace") as f:
            f.write(label[:15])
    except OSError:
        pass
