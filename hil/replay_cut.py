"""What a log begun while the stack ran cannot replay: the rules by which the replay plan leaves a service out
(hil/replay_plan.py says so in a note), and the reader of a device's raw records they share with the replay
devices.

- An I2C driver's chip set-up before the cut (:func:`i2c_setup_recorded`): its identification, configuration
  and calibration are not in the log; the driver declares its identity register (``IDENTITY_REGISTER``).
- An RC mux armed in autonomous mode before the cut (:func:`autonomy_armed_at_start`): the pilot's arming is
  not in the log, and a replayed mux coming out of "no signal" could not grant autonomy.
"""

from __future__ import annotations

import re
from typing import Any, Iterator

from u2sa_hw.recording.log_reader import LogFile
from u2sa_hw.registry import resolve_kind


SETUP_SCAN_READS = 3   # reads of one register with no write before them: the driver was sampling already


def raw_records(log: LogFile, device: str, type_name: str) -> Iterator[tuple[int, Any]]:
    """``(log time ns, record)`` of RAW.*device*'s records of type *type_name*, in log order (a record that
    does not decode is skipped: the replay devices count what they cannot use)."""
    from u2sa_hw.messages import REGISTRY, MalformedMessage

    for m in log.messages(rf"RAW\.{re.escape(device)}"):
        try:
            rec, _ = REGISTRY.decode(m.data)
        except MalformedMessage:
            continue
        if type(rec).__name__ == type_name:
            yield m.log_time_ns, rec


def i2c_setup_recorded(log: LogFile, device: str, *, identity_register: int | None = None) -> bool:
    """True when RAW.*device* holds its driver's chip set-up from its start. With the driver's
    *identity_register* (``DeviceDeclarations.IDENTITY_REGISTER``): the device's first record is a read of
    it. Without: the first record is a read (every supported chip driver reads the chip's identity first)
    and a write follows (it configures the chip; sampling only reads) before any register is read
    SETUP_SCAN_READS times. A recording started while the stack ran (``u2sa record``, a recorder restarted, a
    log recovered after a cut) begins with data reads, or inside the set-up after the identity read (a
    configuration read, then writes: the second rule took that for a set-up): a replay could not identify
    the chip, and its calibration is not in the log. Reads the log only up to that point."""
    from u2sa_hw.ports.i2c.wire import OP_READ, OP_WRITE

    reads: dict[tuple[int, int], int] = {}
    for _t, rec in raw_records(log, device, "RawI2c"):
        if identity_register is not None:
            return rec.op == OP_READ and int(rec.register_address) == identity_register
        if rec.op == OP_WRITE:
            return bool(reads)   # a write first: the recording began inside the set-up, after the identity read
        if rec.op == OP_READ:
            key = (int(rec.address), int(rec.register_address))
            reads[key] = reads.get(key, 0) + 1
            if reads[key] >= SETUP_SCAN_READS:
                return False
    return True   # too few reads to tell: replay it (a short log of set-up reads replays as before)


def autonomy_armed_at_start(log: LogFile, service: str, *, start_ns: int) -> bool:
    """True when *service*'s (an RC mux's) first RC_MODE at or after *start_ns* says it was armed in autonomous
    mode: the pilot armed it through manual before then, which a replay of the window cannot reproduce (a mux
    coming out of "no signal" with the switch at autonomous stays disarmed until the pilot goes through manual).
    Reads the log only up to that message."""
    from u2sa_hw.drivers.rc_mux.pulse import MODE_AUTONOMOUS
    from u2sa_hw.lcmtypes import RcMode

    for m in log.messages(r"RC_MODE"):
        if m.log_time_ns < start_ns:
            continue
        try:
            msg = RcMode.decode(m.data)
        except Exception:  # noqa: BLE001 - a malformed message says nothing about the mux
            continue
        if msg.header.source == service:
            return bool(msg.armed) and msg.mode == MODE_AUTONOMOUS
    return False


def service_kind(services: dict[str, Any], service: str) -> str | None:
    """The kind of *service* in a profile's services table (None: no such service, or no kind)."""
    table = services.get(service)
    kind = table.get("kind") if isinstance(table, dict) else None
    return kind if isinstance(kind, str) else None


def identity_register(services: dict[str, Any], service: str) -> int | None:
    """The chip identity register *service*'s driver declares (None: none, or its kind cannot be loaded)."""
    from u2sa_hw.ports.declared import declarations

    kind = service_kind(services, service)
    try:
        return declarations(resolve_kind(kind)).IDENTITY_REGISTER if isinstance(kind, str) else None
    except (LookupError, ImportError):
        return None
