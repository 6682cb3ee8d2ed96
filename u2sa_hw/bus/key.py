"""The vehicle's bus key: where it lives, how it is read, written and made (DESIGN.md 5b).

A key is 256 random bits stored as one line of 64 hex digits. Every process finds it the
same way (:func:`key_path`): ``$U2SA_BUS_KEY_FILE`` (what ``u2sa sim``, ``u2sa run`` without
an installed key and the tests set to a fresh key of their own), else the profile's
``bus_key``, else ``/etc/u2sa/bus.key`` (made by ``u2sa install``, root:u2sa 0640).

Every failure is a :class:`BusKeyError` of one line naming the file and the fix.
"""

from __future__ import annotations

import contextlib
import errno
import grp
import hashlib
import os
import stat
from pathlib import Path

KEY_ENV = "U2SA_BUS_KEY_FILE"
SYSTEM_KEY = Path("/etc/u2sa/bus.key")
KEY_BYTES = 32
KEY_GROUP = "u2sa"
KEY_ID_BYTES = 4


class BusKeyError(RuntimeError):
    """The bus key cannot be used; the message names the file and the fix."""


def key_path(profile_key: Path | str | None = None, *, env: dict[str, str] | None = None) -> Path:
    """The key file this process uses: ``$U2SA_BUS_KEY_FILE``, else *profile_key*, else /etc/u2sa/bus.key."""
    environ = os.environ if env is None else env
    chosen = environ.get(KEY_ENV) or profile_key
    return Path(chosen).expanduser() if chosen else SYSTEM_KEY


def key_id(key: bytes) -> bytes:
    """The key's public 4-byte id: it names the key in every trailer (and on ``u2sa key show --id``)."""
    return hashlib.sha256(b"u2sa bus key id\0" + key).digest()[:KEY_ID_BYTES]


def parse_key(text: str | bytes, *, source: str) -> bytes:
    """The 32 key bytes of a key file's text (64 hex digits); BusKeyError naming *source* otherwise."""
    if isinstance(text, bytes):
        try:
            text = text.decode("ascii")
        except UnicodeDecodeError:
            raise BusKeyError(f"{source}: not a bus key (a bus key is one line of {2 * KEY_BYTES} hex digits); "
                              f"{_FIX}") from None
    digits = text.strip()
    if len(digits) != 2 * KEY_BYTES:
        raise BusKeyError(f"{source}: a bus key is {2 * KEY_BYTES} hex digits (256 bits), this one has "
                          f"{len(digits)} characters; {_FIX}")
    try:
        return bytes.fromhex(digits)
    except ValueError:
        raise BusKeyError(f"{source}: a bus key is {2 * KEY_BYTES} hex digits, this one has other characters; "
                          f"{_FIX}") from None


_FIX = ("make a new one with 'sudo u2sa key rotate' or copy the vehicle's with "
        "'u2sa key show' there and 'sudo u2sa key import FILE' here")


def read_key(path: Path) -> bytes:
    """The key stored at *path*; BusKeyError (missing, unreadable, wrong length) with the fix."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise BusKeyError(f"no bus key at {path}: 'sudo u2sa install' (or 'sudo u2sa key rotate') makes one; "
                          f"without root: 'u2sa key rotate --file ~/.u2sa/bus.key' and export "
                          f"{KEY_ENV}=~/.u2sa/bus.key; a bench without signing can set bus_security = \"open\" "
                          "in the vehicle profile") from None
    except PermissionError:
        raise BusKeyError(f"cannot read the bus key {path} (permission denied): add yourself to the group "
                          f"{KEY_GROUP} ('sudo usermod -aG {KEY_GROUP} $USER', then log in again) or use sudo") from None
    except OSError as exc:
        raise BusKeyError(f"cannot read the bus key {path}: {exc.strerror or exc}; {_FIX}") from None
    return parse_key(data, source=str(path))


def new_key() -> bytes:
    """256 fresh random bits."""
    return os.urandom(KEY_BYTES)


def write_key(path: Path, key: bytes, *, group: str | None = KEY_GROUP) -> None:
    """Store *key* at *path* atomically (temp file, fsync, rename), mode 0640 root:*group* when root can.

    Without root, or without the group on this machine, the file is the caller's, mode 0600.
    A key replaced (rotate, import) keeps the old file's group and mode, never wider than 0640.
    """
    if len(key) != KEY_BYTES:
        raise BusKeyError(f"{path}: refusing to write a {len(key)}-byte key (a bus key is {KEY_BYTES} bytes)")
    root = os.geteuid() == 0
    try:
        old = path.stat()
    except OSError:
        gid = _group_id(group) if root and group else None
        mode = 0o640 if gid is not None else 0o600
    else:
        gid = old.st_gid if root else None
        mode = stat.S_IMODE(old.st_mode) & 0o640 or 0o600
    write_key_file(path, key, mode=mode, gid=gid)


def write_key_file(path: Path, key: bytes, *, mode: int, gid: int | None) -> None:
    """Store *key* as one line of hex at *path* atomically (temp file, fsync, rename), *mode*, root:*gid* if given."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        import tempfile   # only where a key is written, not in every service that reads one
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    except OSError as exc:
        raise BusKeyError(_write_error(path, exc)) from None
    try:
        with os.fdopen(fd, "w") as f:
            if gid is not None:
                os.fchown(f.fileno(), 0, gid)
            os.fchmod(f.fileno(), mode)
            f.write(key.hex() + "\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise BusKeyError(_write_error(path, exc)) from None


def ensure_key(path: Path, *, group: str | None = KEY_GROUP) -> bool:
    """Make a key at *path* unless one is there; True when it made one (what ``u2sa install`` does)."""
    if path.exists():
        return False
    write_key(path, new_key(), group=group)
    return True


def _group_id(name: str) -> int | None:
    try:
        return grp.getgrnam(name).gr_gid
    except KeyError:
        return None


def _write_error(path: Path, exc: OSError) -> str:
    if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        return f"cannot write the bus key {path} ({exc.strerror}): run the command with sudo, or pass --file PATH"
    return f"cannot write the bus key {path}: {exc.strerror or exc}"
