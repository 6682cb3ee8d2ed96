"""Checking a log's recorded pilot messages with the pilot's public key the log names.

The recorder keeps the pilot's 88-byte Ed25519 trailer after every RC_MODE and MANUAL_CMD it
writes and the pilot's public key in the ``u2sa`` metadata record (``pilot_key``, 64 hex
digits, and ``pilot_key_id``; u2sa_hw.recording.mcap_log). :func:`check_log` checks every
recorded pilot message's signature with that key (``u2sa replay`` and ``replay-check`` report
it; a failure is a finding of ``--compare``). Only the signature is checked: the counters and
the freshness window were the live receivers' business.

What it can say (:meth:`PilotCheck.line`):

- ``pilot messages: 412 checked with the recorded pilot key 3ec94b6c, all signed``;
- how many failed: *unsigned* (no pilot trailer: stripped, or written by something else than
  the recorder) and *forged* (a signature that does not check with the recorded key: the
  message, its trailer or the key in the metadata was changed), with the first few;
- a note, nothing checked: a log recorded before pilot signatures existed (no ``pilot_key``
  in its metadata), one recorded on an open bus or by a recorder that had no pilot public key,
  or one whose recorded key is malformed.

The key comes from the log itself, so the check says the log is consistent, not who made it:
compare ``pilot_key_id`` with the vehicle's (``u2sa key show --pilot``) to know that (docs/security.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from u2sa_hw.bus.roles import PILOT_CHANNELS

PILOT_KEY = "pilot_key"         # in the ``u2sa`` metadata record: the public key, hex
PILOT_KEY_ID = "pilot_key_id"   # ... its id, hex (u2sa_hw.bus.pilot.pilot_key_id)
RUN_METADATA = "u2sa"
SHOWN_FAILURES = 5


@dataclass
class Failure:
    """One recorded pilot message that fails the check."""

    channel: str
    t_ns: int
    why: str            # "unsigned" or "forged"


@dataclass
class PilotCheck:
    """The outcome of :func:`check_log`."""

    key_id: str = ""                 # the recorded key's id (hex), "" when nothing could be checked
    checked: int = 0                 # pilot messages checked with it
    unsigned: int = 0                # ... without a pilot trailer
    forged: int = 0                  # ... whose signature does not check with the recorded key
    failures: list[Failure] = field(default_factory=list)   # the first few
    note: str = ""                   # why nothing was checked ("" when the key was used)
    origin_ns: int = 0               # report times count from here (the window's start)

    @property
    def failed(self) -> int:
        """Pilot messages that fail the check."""
        return self.unsigned + self.forged

    @property
    def ok(self) -> bool:
        """False when a recorded pilot message fails the check (a note alone is not a failure)."""
        return self.failed == 0

    def short(self) -> str:
        """The failure in a few words, for a summary line ("" when none)."""
        if self.ok:
            return ""
        return (f"{self.failed} of {self.checked} recorded pilot messages fail the check with the recorded pilot key "
                f"{self.key_id} ({_counts(self)})")

    def line(self) -> str:
        """One line: checked and all signed, how many failed (and the first ones), or why nothing was checked."""
        if self.note:
            return f"pilot messages: not checked: {self.note}"
        if not self.checked:
            return f"pilot messages: none recorded (recorded pilot key {self.key_id})"
        if self.ok:
            return f"pilot messages: {self.checked} checked with the recorded pilot key {self.key_id}, all signed"
        first = "; ".join(f"{f.channel} at t={(f.t_ns - self.origin_ns) / 1e9:.3f} s {f.why}"
                          for f in self.failures[:SHOWN_FAILURES])
        more = f"; and {self.failed - SHOWN_FAILURES} more" if self.failed > SHOWN_FAILURES else ""
        return (f"pilot messages: {self.failed} of {self.checked} FAIL the check with the recorded pilot key "
                f"{self.key_id} ({_counts(self)}): {first}{more}")

    def to_dict(self) -> dict[str, Any]:
        """For ``--json``."""
        return {"ok": self.ok, "key_id": self.key_id, "checked": self.checked, "unsigned": self.unsigned,
                "forged": self.forged, "note": self.note, "line": self.line(),
                "failures": [{"channel": f.channel, "t_s": (f.t_ns - self.origin_ns) / 1e9, "why": f.why}
                             for f in self.failures]}


def _counts(c: PilotCheck) -> str:
    return ", ".join(f"{what} {n}" for what, n in (("forged", c.forged), ("unsigned", c.unsigned)) if n)


def recorded_verifier(metadata: dict[str, dict[str, str]]) -> tuple[Any, str]:
    """(the verifier of the log's recorded pilot key, "") or (None, why nothing can be checked)."""
    run = metadata.get(RUN_METADATA)
    if run is None or PILOT_KEY not in run:
        return None, "this log has no pilot signatures (recorded before they existed)"
    text = run.get(PILOT_KEY, "").strip()
    if not text:
        if run.get("bus_security") == "open":
            return None, "this log has no pilot signatures (recorded on an open bus: nothing was signed)"
        return None, "this log has no pilot signatures (its recorder had no pilot public key, pilot.pub)"
    shown = text if len(text) <= 72 else text[:72] + "..."
    try:
        public = bytes.fromhex(text)
    except ValueError:
        public = b""
    if len(public) != 32:
        return None, f"the log's recorded pilot key is malformed ({PILOT_KEY} {shown!r} is not 64 hex digits)"
    from u2sa_hw.bus.pilot import PilotVerifier, pilot_key_id

    kid = pilot_key_id(public).hex()
    named = run.get(PILOT_KEY_ID, "").strip().lower()
    if named and named != kid:
        return None, (f"the log's recorded pilot key is malformed ({PILOT_KEY_ID} {named[:16]!r} is not the id of "
                      f"its {PILOT_KEY}, {kid})")
    try:
        verifier = PilotVerifier(public)
    except Exception as exc:  # noqa: BLE001 - any refusal of the key bytes is a malformed key, said in one line
        return None, f"the log's recorded pilot key is malformed ({PILOT_KEY} {shown!r}: {exc})"
    return verifier, ""


def check_log(path: Path | str, *, start_ns: int | None = None, end_ns: int | None = None) -> PilotCheck:
    """Check every recorded pilot message (within [start_ns, end_ns] when given) with the log's recorded pilot key.

    Never raises for what the log holds: a missing or malformed key is the result's ``note``;
    a damaged tail ends the check where reading ends (LogError only when *path* is no log).
    """
    from u2sa_hw.bus.auth import OK, UNSIGNED, check_pilot_packet
    from u2sa_hw.recording.log_reader import LogFile

    log = LogFile(path)
    result = PilotCheck(origin_ns=start_ns or 0)
    verifier: Any = None
    resolved = False
    pending: list[tuple[str, int, bytes]] = []   # pilot messages read before the log's metadata (another tool's log)

    def check(channel: str, t_ns: int, data: bytes) -> None:
        verdict = check_pilot_packet(channel, data, verifier)
        result.checked += 1
        if verdict is OK:
            return
        if verdict is UNSIGNED:
            result.unsigned += 1
        else:
            result.forged += 1
        if len(result.failures) < SHOWN_FAILURES:
            result.failures.append(Failure(channel, t_ns, verdict))

    for channel, t_ns, data in log.selected(lambda c: c in PILOT_CHANNELS, raw=True):
        if start_ns is not None and t_ns < start_ns:
            continue
        if end_ns is not None and t_ns > end_ns:
            break
        if not result.origin_ns:
            result.origin_ns = t_ns
        if not resolved:
            if RUN_METADATA not in log.contents.metadata:
                pending.append((channel, t_ns, data))
                continue
            verifier, result.note = recorded_verifier(log.contents.metadata)
            resolved = True
            if result.note:
                break   # nothing can be checked: the rest of the log need not be read
        check(channel, t_ns, data)
    if not resolved:
        verifier, result.note = recorded_verifier(log.contents.metadata)
        if not result.note:
            for item in pending:
                check(*item)
    if not result.note:
        result.key_id = verifier.id.hex()
    return result
