"""Fingerprint registry and extension-aware decoding (DESIGN.md section 2, requirement M6).

Every LCM type carries an 8-byte fingerprint. A child type's first field is its parent
(``base``); LCM encodes nested structs without their fingerprint, so the bytes after a
child's fingerprint begin with an encoding of its parent. A receiver that subscribed
with a base type therefore decodes a child it has never heard of as that base type.
"""

from __future__ import annotations

import struct
import threading
from io import BytesIO
from typing import Any, Mapping

from u2sa_hw import lcmtypes

# Fingerprints of types as they were before a field was renamed: the bytes are laid out the
# same (LCM hashes the field names into the fingerprint, not into the encoding), so a message
# recorded with the old fingerprint decodes as today's type. Never remove an entry: old logs
# must keep replaying.
LEGACY_FINGERPRINTS: dict[bytes, tuple[str, str]] = {
    # RawI2c.register (a C/C++ keyword: lcm-gen's C and C++ output did not compile) became register_address
    bytes.fromhex("0e61df589a1e329c"): ("RawI2c", "RawI2c with its field 'register' (before 2026-11)"),
}


class MalformedMessage(ValueError):
    """Bytes on a channel that do not decode as the channel's type (or any descendant)."""


def fingerprint_of(cls: type) -> bytes:
    """The 8-byte packed fingerprint of an LCM type."""
    return cls._get_packed_fingerprint()


def type_name(cls_or_msg: Any) -> str:
    """The short type name of an LCM class or message (``StateInformation``)."""
    cls = cls_or_msg if isinstance(cls_or_msg, type) else type(cls_or_msg)
    return cls.__name__


class TypeRegistry:
    """Maps fingerprints and names to LCM classes and knows each class's parent.

    With *package* (a generated package whose ``_TYPES`` load on first use, as
    ``u2sa_hw.lcmtypes``) it starts empty and registers a type when it is first asked for:
    a decode by a subscription's own type, a name, and, on any fingerprint it does not know
    yet, every type of the package at once (and *legacy*: old fingerprint -> type name), so
    an answer of "unknown" is always about every type. A service process thus loads only the
    types it receives and sends.
    """

    def __init__(self, *, package: Any = None, legacy: Mapping[bytes, str] | None = None) -> None:
        self._by_fp: dict[bytes, type] = {}
        self._by_name: dict[str, type] = {}
        self._ancestry: dict[type, tuple[type, ...]] = {}   # parent_of builds an instance: once per class
        self._package = package
        self._legacy = dict(legacy or {})
        self._complete = package is None
        self._fill_lock = threading.Lock()

    def _fill(self) -> None:
        """Register every type of the package (importing each), once."""
        with self._fill_lock:
            if self._complete:
                return
            for name in self._package._TYPES:
                cls = getattr(self._package, name)
                if self._by_fp.get(fingerprint_of(cls)) is not cls:
                    self.register(cls)
            for fp, name in self._legacy.items():
                self.register_legacy(fp, getattr(self._package, name))
            self._complete = True

    def _known(self, fp: bytes) -> type | None:
        cls = self._by_fp.get(fp)
        if cls is None and not self._complete:
            self._fill()
            cls = self._by_fp.get(fp)
        return cls

    def register(self, cls: type) -> type:
        """Add an LCM class (its parent is found through its ``base`` field); returns it."""
        fp = fingerprint_of(cls)
        other = self._by_fp.get(fp)
        if other is not None and other is not cls:
            raise ValueError(
                f"{cls.__name__} has the same LCM fingerprint as {other.__name__}: LCM hashes field "
                "names and types, not struct names, so give one of them a distinct field"
            )
        self._by_fp[fp] = cls
        self._by_name[cls.__name__] = cls
        self._by_name[f"{cls.__module__.rsplit('.', 1)[0]}.{cls.__name__}"] = cls
        return cls

    def register_legacy(self, fp: bytes, cls: type) -> None:
        """Decode the old fingerprint *fp* of *cls* (a field renamed, the bytes the same) as *cls*."""
        other = self._by_fp.get(fp)
        if other is not None and other is not cls:
            raise ValueError(f"legacy fingerprint {fp.hex()} of {cls.__name__} is {other.__name__}'s")
        self._by_fp[fp] = cls

    def by_fingerprint(self, fp: bytes) -> type | None:
        """The class whose fingerprint is *fp*, or None."""
        return self._known(fp)

    def by_name(self, name: str) -> type:
        """The class called *name* (short or package-qualified); KeyError lists the known ones."""
        found = self._by_name.get(name)
        if found is not None:
            return found
        short = name.rpartition(".")[2]
        if self._package is not None and short in self._package._TYPES and name in (
                short, f"{self._package.__name__}.{short}"):
            cls = getattr(self._package, short)
            if self._by_fp.get(fingerprint_of(cls)) is not cls:
                self.register(cls)
            return cls
        self._fill()
        try:
            return self._by_name[name]
        except KeyError:
            known = ", ".join(sorted(n for n in self._by_name if "." not in n))
            raise KeyError(f"unknown message type {name!r}; known types: {known}") from None

    def names(self) -> list[str]:
        """Short names of every registered type."""
        if not self._complete:
            self._fill()
        return sorted(n for n in self._by_name if "." not in n)

    @staticmethod
    def parent_of(cls: type) -> type | None:
        """The parent type of an extension (its first field, named ``base``), or None."""
        slots = getattr(cls, "__slots__", [])
        if not slots or slots[0] != "base":
            return None
        return type(cls().base)

    def ancestry(self, cls: type) -> list[type]:
        """*cls* followed by its parents up to the root type."""
        return list(self._chain(cls))

    def _chain(self, cls: type) -> tuple[type, ...]:
        chain = self._ancestry.get(cls)
        if chain is None:
            found = [cls]
            while (parent := self.parent_of(found[-1])) is not None:
                found.append(parent)
            chain = self._ancestry[cls] = tuple(found)
        return chain

    def is_a(self, cls: type, base: type) -> bool:
        """True when *cls* is *base* or extends it (at any depth)."""
        return base in self._chain(cls)

    def decode(self, data: bytes, base: type | None = None) -> tuple[Any, bool]:
        """Decode *data*; return ``(message, known)``.

        A known fingerprint decodes to its concrete type (which must extend *base* when
        given). An unknown fingerprint decodes as *base* (``known`` is False). Anything
        else raises :class:`MalformedMessage` with the reason.
        """
        if len(data) < 8:
            raise MalformedMessage(f"truncated: {len(data)} bytes, shorter than a fingerprint")
        fp = data[:8]
        cls = self._by_fp.get(fp)
        if cls is None and not self._complete:
            # the subscription's own type, the common case, registers without loading the others
            if base is not None and fp == fingerprint_of(base):
                cls = self.register(base)
            else:
                cls = self._known(fp)
        if cls is not None:
            if base is not None and cls is not base and not self.is_a(cls, base):
                raise MalformedMessage(f"wrong type: {cls.__name__} is not a {base.__name__}")
            return _decode_body(cls, data), True
        if base is None:
            raise MalformedMessage(f"unknown fingerprint {data[:8].hex()}")
        return _decode_body(base, data), False


def _decode_body(cls: type, data: bytes) -> Any:
    buf = BytesIO(data)
    buf.seek(8)
    try:
        msg = cls._decode_one(buf)
    except (struct.error, ValueError, UnicodeDecodeError, OverflowError, MemoryError, IndexError) as exc:
        raise MalformedMessage(f"truncated or garbage {cls.__name__}: {exc}") from None
    if buf.tell() > len(data):
        raise MalformedMessage(f"truncated {cls.__name__}")
    return msg


def as_type(msg: Any, cls: type) -> Any:
    """View *msg* as its ancestor *cls* (following ``base`` fields); TypeError if it is not one."""
    cur = msg
    while not isinstance(cur, cls):
        if not hasattr(cur, "base") or not hasattr(type(cur), "_get_packed_fingerprint"):
            raise TypeError(f"{type(msg).__name__} is not a {cls.__name__}")
        cur = cur.base
    return cur


REGISTRY = TypeRegistry(package=lcmtypes, legacy={fp: name for fp, (name, _what) in LEGACY_FINGERPRINTS.items()})
