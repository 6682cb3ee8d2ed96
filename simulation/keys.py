"""The pilot's RC transmitter on the keyboard, for ``u2sa sim`` and ``u2sa mock`` on a terminal.

==========  ================================================================
``w`` `s`   throttle stick up / down by STEP (-1..1; 0 = centre)
``a`` `d`   steering stick left / right by STEP
space       both sticks back to the centre
``m``       flip the mode switch (manual <-> autonomous)
``l``       the RC link lost / back (the receiver stops its pulses)
==========  ================================================================

The stick channels are the profile's ``[safety.manual_mixer]`` ``throttle_channel`` and
``steering_channel`` (default ``throttle`` and ``steering``). The terminal is put in cbreak
mode (keys arrive without Enter, Ctrl-C still interrupts) and restored on stop.
"""

from __future__ import annotations

import os
import select
import sys
import threading
from typing import Any, Callable

STEP = 0.1
HELP = "w/s throttle, a/d steering, space centre, m mode switch, l RC link"


def stick_channels(profile: Any) -> tuple[str, str]:
    """(throttle channel, steering channel) from the profile's ``[safety.manual_mixer]``."""
    safety = profile.raw.get("safety", {}) if profile is not None else {}
    mixer = safety.get("manual_mixer", {}) if isinstance(safety, dict) else {}
    mixer = mixer if isinstance(mixer, dict) else {}
    return str(mixer.get("throttle_channel", "throttle")), str(mixer.get("steering_channel", "steering"))


class StickKeys:
    """Reads single keys from stdin and moves the sticks of the mocks that *mocks()* returns (None: not yet)."""

    def __init__(self, mocks: Callable[[], Any], *, say: Callable[[str], None],
                 extra: dict[str, tuple[str, Callable[[], None]]] | None = None) -> None:
        self.mocks = mocks
        self.say = say
        self.extra = dict(extra or {})
        self.throttle = 0.0
        self.steering = 0.0
        self.autonomous = False
        self.link_lost = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._saved: Any = None

    def start(self) -> "StickKeys":
        """Put the terminal in cbreak mode and start reading keys."""
        import termios
        import tty

        fd = sys.stdin.fileno()
        self._saved = termios.tcgetattr(fd)
        tty.setcbreak(fd)
        self._thread = threading.Thread(target=self._run, args=(fd,), name="stick-keys", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop reading and restore the terminal."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
        if self._saved is not None:
            import termios

            termios.tcsetattr(sys.stdin.fileno(), termios.TCSADRAIN, self._saved)
            self._saved = None

    def press(self, key: str) -> str | None:
        """Act on one key; returns what was done (None for a key that means nothing)."""
        mocks = self.mocks()
        if key in self.extra:
            self.extra[key][1]()
            return self.extra[key][0]
        if mocks is None:
            return None
        throttle_ch, steering_ch = stick_channels(getattr(mocks, "profile", None))
        if key in "wsad ":
            if key == " ":
                self.throttle = self.steering = 0.0
            elif key in "ws":
                self.throttle = round(max(-1.0, min(1.0, self.throttle + (STEP if key == "w" else -STEP))), 2)
            else:
                self.steering = round(max(-1.0, min(1.0, self.steering + (STEP if key == "d" else -STEP))), 2)
            mocks.set_sticks(**{throttle_ch: self.throttle, steering_ch: self.steering})
            return f"sticks: {throttle_ch} {self.throttle:+.1f}, {steering_ch} {self.steering:+.1f}"
        if key == "m":
            self.autonomous = not self.autonomous
            mocks.set_mode_switch(self.autonomous)
            return f"pilot: mode switch {'AUTONOMOUS' if self.autonomous else 'MANUAL'}"
        if key == "l":
            self.link_lost = not self.link_lost
            mocks.signal_loss(self.link_lost)
            return "RC link LOST" if self.link_lost else "RC link back"
        return None

    def _run(self, fd: int) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([fd], [], [], 0.2)
            if not ready:
                continue
            data = os.read(fd, 1)
            if not data:
                return
            key = data.decode(errors="replace").lower()
            try:
                done = self.press(key)
            except ValueError as exc:   # a profile whose receiver lacks a stick channel
                done = f"keys: {exc}"
            if done is None and key not in ("\n", "\r"):
                done = HELP + "".join(f", {k} {what}" for k, (what, _) in self.extra.items())
            if done:
                self.say(done)
