"""Kernel-side channel filter for a transport's LCM receive socket.

LCM over UDP multicast delivers every packet on the bus to every process: a service that takes
two channels still wakes for each of the hundreds of messages a second the others publish,
only for LCM to drop them in user space. On a 4-core SBC running ten services that is much
of the CPU the bus costs, and in a ``--fast`` replay about a fifth of all the work.

A socket filter (classic BPF, ``SO_ATTACH_FILTER``) on the receive socket lets the kernel drop
those packets before anything wakes. The program reads LCM's packet header (LCM's UDP
multicast wire format):

- ``LC02`` (a whole message): magic, sequence number, then the channel name, NUL-terminated.
- ``LC03`` (a fragment of a large one): magic, sequence number, size, offset, fragment number,
  fragment count, and the channel name only in fragment 0. Fragment 0 is kept or dropped by
  its channel; later fragments always pass (LCM discards a fragment it holds no message for).
- anything else passes: LCM's own checks handle it as before; a packet too short to hold the
  header it claims is dropped (LCM discards it too).

Only exact channel names are filtered; one regex subscription (the recorder's ``.*``) removes
the filter. ``LCM_SELF_TEST`` always passes. The filter is a saving, never a gate: where it cannot
be attached or does not behave as expected (:func:`works` probes the kernel once per process
on a private loopback socket), the socket stays unfiltered and everything works as before.
The dropped packets show as ``drops`` of the service's socket in /proc/net/udp and as receive
errors in ``netstat -su``; they are not losses (docs/security.md).
"""

from __future__ import annotations

import ctypes
import functools
import logging
import socket
import struct
from typing import Iterable

log = logging.getLogger("u2sa_hw.bus.filter")

SO_ATTACH_FILTER = getattr(socket, "SO_ATTACH_FILTER", 26)
SO_DETACH_FILTER = getattr(socket, "SO_DETACH_FILTER", 27)
UDP_HEADER = 8          # a UDP socket filter sees the datagram from its UDP header on
MAGIC_SHORT = 0x4C433032  # "LC02"
MAGIC_LONG = 0x4C433033   # "LC03"
SHORT_HEADER = 8        # magic, seqno
LONG_HEADER = 20        # magic, seqno, size, offset, fragment no (u16), fragments (u16)
FRAGMENT_NO_AT = 16     # the fragment number's offset in a long header
ALWAYS = ("LCM_SELF_TEST",)
MAX_INSNS = 4096        # the kernel's BPF_MAXINSNS

# classic BPF opcodes (linux/filter.h)
_LD_W, _LD_H, _LD_B = 0x20, 0x28, 0x30        # BPF_LD | size | BPF_ABS
_JEQ, _JA, _RET = 0x15, 0x05, 0x06            # BPF_JMP|BPF_JEQ|BPF_K, BPF_JMP|BPF_JA, BPF_RET|BPF_K
_LD_LEN, _JGE = 0x80, 0x35                    # BPF_LD|BPF_W|BPF_LEN (the packet's length), BPF_JMP|BPF_JGE|BPF_K
_ACCEPT, _DROP = 0xFFFFFFFF, 0
_Insn = tuple[int, int, int, int]              # code, jt, jf, k


class FilterTooLarge(ValueError):
    """The channel list needs more instructions than the kernel takes."""


def _match_block(name: str, base: int) -> list[_Insn]:
    """Accept when the NUL-terminated *name* is at offset *base*; else fall through past the block."""
    raw = name.encode() + b"\0"
    steps: list[tuple[int, int, int]] = []     # (load code, offset, value)
    pos = 0
    while pos < len(raw):
        size = 4 if len(raw) - pos >= 4 else 2 if len(raw) - pos >= 2 else 1
        code = {4: _LD_W, 2: _LD_H, 1: _LD_B}[size]
        steps.append((code, UDP_HEADER + base + pos, int.from_bytes(raw[pos:pos + size], "big")))
        pos += size
    # A load past the packet's end would end the whole program with a drop: a packet too short to hold
    # this name (a short message on a channel later in the list) skips the block instead.
    block: list[_Insn] = [(_LD_LEN, 0, 0, 0), (_JGE, 0, 2 * len(steps) + 1, UDP_HEADER + base + len(raw))]
    for i, (code, offset, value) in enumerate(steps):
        left = len(steps) - i - 1                   # compare pairs after this one
        block.append((code, 0, 0, offset))
        block.append((_JEQ, 0, 2 * left + 1, value))  # a mismatch skips the rest and the accept
    block.append((_RET, 0, 0, _ACCEPT))
    return block


def program(channels: Iterable[str]) -> list[_Insn]:
    """The filter that passes LCM packets on *channels* (plus :data:`ALWAYS`) and anything not LCM."""
    names = sorted(set(channels) | set(ALWAYS))
    short = [i for n in names for i in _match_block(n, SHORT_HEADER)] + [(_RET, 0, 0, _DROP)]
    long_ = [(_LD_H, 0, 0, UDP_HEADER + FRAGMENT_NO_AT), (_JEQ, 1, 0, 0), (_RET, 0, 0, _ACCEPT)]
    long_ += [i for n in names for i in _match_block(n, LONG_HEADER)] + [(_RET, 0, 0, _DROP)]
    head: list[_Insn] = [
        (_LD_W, 0, 0, UDP_HEADER),            # 0: the magic
        (_JEQ, 0, 1, MAGIC_SHORT),            # 1: LC02 -> 2, else -> 3
        (_JA, 0, 0, 3),                       # 2: -> the short block (6)
        (_JEQ, 0, 1, MAGIC_LONG),             # 3: LC03 -> 4, else -> 5
        (_JA, 0, 0, 1 + len(short)),          # 4: -> the long block (6 + len(short))
        (_RET, 0, 0, _ACCEPT),                # 5: not LCM's: LCM decides
    ]
    insns = head + short + long_
    if len(insns) > MAX_INSNS:
        raise FilterTooLarge(f"{len(names)} channels need {len(insns)} BPF instructions (at most {MAX_INSNS})")
    return insns


def _attach(sock: socket.socket, insns: list[_Insn]) -> None:
    code = b"".join(struct.pack("HBBI", *i) for i in insns)
    buf = ctypes.create_string_buffer(code, len(code))
    sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, struct.pack("HL", len(insns), ctypes.addressof(buf)))


def lcm_packet(channel: str, *, long: bool = False, fragment: int = 0, payload: bytes = b"payload") -> bytes:
    """An LCM packet on *channel* as the filter sees it: a whole message (LC02), or with *long* fragment
    *fragment* of a large one (LC03; only fragment 0 names the channel). For the kernel probe and tests."""
    if not long:
        return struct.pack(">II", MAGIC_SHORT, 1) + channel.encode() + b"\0" + payload
    head = struct.pack(">IIIIHH", MAGIC_LONG, 1, 100_000, 0 if fragment == 0 else 60_000, fragment, 2)
    return head + (channel.encode() + b"\0" + payload if fragment == 0 else payload)


@functools.lru_cache(maxsize=1)
def works() -> bool:
    """True when the kernel runs this module's programs as intended (probed once, on loopback)."""
    try:
        rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    except OSError:
        return False
    with rx, tx:
        try:
            rx.bind(("127.0.0.1", 0))
            rx.setblocking(False)
            _attach(rx, program(["WANTED", "W"]))
            probes = [(lcm_packet("WANTED"), True), (lcm_packet("WANTED_NOT"), False), (lcm_packet("W"), True),
                      (lcm_packet("W", payload=b""), True), (lcm_packet("WANTED", payload=b""), True),
                      (lcm_packet("WANTE"), False), (lcm_packet("WANTED", long=True), True),
                      (lcm_packet("OTHER", long=True), False), (lcm_packet("", long=True, fragment=1), True),
                      (b"not lcm", True)]
            got = []
            for data, _ in probes:
                tx.sendto(data, rx.getsockname())   # loopback delivers within sendto
            while True:
                try:
                    got.append(rx.recv(256))
                except BlockingIOError:
                    break
        except OSError as exc:
            log.info("bus channel filter unavailable (%s): every service hears the whole bus", exc)
            return False
    if got != [data for data, wanted in probes if wanted]:
        log.info("bus channel filter disabled: the kernel's socket filter did not pass the expected packets")
        return False
    return True


def _detach(sock: socket.socket) -> None:
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_DETACH_FILTER, 0)
    except OSError:
        pass   # no filter attached


def apply(fds: Iterable[int], port: int, channels: Iterable[str] | None) -> bool:
    """Filter the UDP sockets among *fds* bound to *port* to *channels* (None: remove the filter).

    True when every such socket is filtered afterwards; False when they all hear everything
    (a filter that cannot be attached to one is removed from all: an older, narrower filter
    left in place would drop a channel subscribed since).
    """
    insns = None
    if channels is not None and works():
        try:
            insns = program(channels)
        except FilterTooLarge as exc:
            log.info("bus channel filter not used: %s", exc)
    socks = []
    for fd in fds:
        try:
            sock = socket.socket(fileno=fd)
        except OSError:
            continue
        try:
            ours = sock.family == socket.AF_INET and sock.type == socket.SOCK_DGRAM and sock.getsockname()[1] == port
        except OSError:
            ours = False
        if ours:
            socks.append(sock)
        else:
            sock.detach()   # the fd is LCM's (or another part's): never close it here
    try:
        if insns is not None:
            try:
                for sock in socks:
                    _attach(sock, insns)
                return bool(socks)
            except OSError as exc:
                log.info("bus channel filter not attached (%s): this process hears the whole bus", exc)
        for sock in socks:
            _detach(sock)
        return False
    finally:
        for sock in socks:
            sock.detach()
