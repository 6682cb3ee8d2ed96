"""The pilot's key pair: only the RC mux can sign RC_MODE and MANUAL_CMD (docs/security.md).

The bus key is shared (HMAC: whoever can check a message can make one), so the pilot's
channels are signed with Ed25519 instead. The private key (``pilot.key``) is readable only by
the RC mux's unit; every receiver holds the public key (``pilot.pub``) and can check a pilot
message without being able to make one. Both files sit beside the bus key (:func:`pilot_paths`):
/etc/u2sa/pilot.key (root:u2sa-pilot 0040, see :data:`PILOT_GROUP`) and /etc/u2sa/pilot.pub
(0644) on an installed vehicle, a run's or a test's own pair beside its own bus key.

Each file is one line of 64 hex digits: the 32-byte Ed25519 seed or public key. The key id
(4 bytes, in every pilot trailer) names the public key, so a receiver tells a rotated or
another vehicle's pilot key from a forgery without trying it.

PyNaCl (pyca's binding of libsodium) does the Ed25519, imported only by a process that signs
or checks a pilot message. It was chosen over ``cryptography`` for the lean stack: on this
project's bench machine it checks a signature in about 37 µs against 60 µs, and adds about
2 MB to a process against 9 MB (bench/pilot_cost.py, docs/security.md).
"""

from __future__ import annotations

import grp
import hashlib
import os
from pathlib import Path

from u2sa_hw.bus.key import KEY_BYTES, BusKeyError, parse_key, write_key_file

PILOT_KEY_NAME = "pilot.key"
PILOT_PUB_NAME = "pilot.pub"
PILOT_GROUP = "u2sa-pilot"     # the group of the RC mux's unit alone: the only reader of pilot.key
SIGNATURE_BYTES = 64
KEY_ID_BYTES = 4


def pilot_paths(bus_key_file: Path) -> tuple[Path, Path]:
    """(private, public) key files of the pilot beside the bus key *bus_key_file*."""
    directory = Path(bus_key_file).parent
    return directory / PILOT_KEY_NAME, directory / PILOT_PUB_NAME


def pilot_key_id(public: bytes) -> bytes:
    """The 4-byte id of a pilot public key (in every pilot trailer, and on ``u2sa key show --pilot``)."""
    return hashlib.sha256(b"u2sa pilot key id\0" + public).digest()[:KEY_ID_BYTES]


class PilotSigner:
    """Signs with the pilot's private key (the RC mux; a test or a sim's own RC mux)."""

    def __init__(self, seed: bytes) -> None:
        from nacl.signing import SigningKey

        self._key = SigningKey(seed)
        self.id = pilot_key_id(bytes(self._key.verify_key))

    def sign(self, data: bytes) -> bytes:
        """The 64-byte Ed25519 signature of *data*."""
        return self._key.sign(data).signature


class PilotVerifier:
    """Checks pilot signatures with the public key; cannot make one."""

    def __init__(self, public: bytes) -> None:
        from nacl.exceptions import BadSignatureError
        from nacl.signing import VerifyKey

        self._key = VerifyKey(public)
        self._invalid = BadSignatureError
        self.id = pilot_key_id(public)
        self.public = public

    def check(self, signature: bytes, data: bytes) -> bool:
        """True when *signature* is the pilot's over *data*."""
        try:
            self._key.verify(data, signature)
        except self._invalid:
            return False
        return True


def read_signer(path: Path) -> PilotSigner:
    """The pilot's signer from its private key file; BusKeyError naming the file and the fix."""
    return PilotSigner(_read(path, "pilot's private key", _PRIVATE_FIX))


def read_verifier(path: Path) -> PilotVerifier:
    """The pilot's public key from *path*; BusKeyError naming the file and the fix."""
    return PilotVerifier(_read(path, "pilot's public key", _PUBLIC_FIX))


_PRIVATE_FIX = ("only the RC mux signs RC_MODE and MANUAL_CMD: 'sudo u2sa install' makes the pair "
                f"and gives the RC mux's unit the group {PILOT_GROUP}; 'u2sa key pilot --file BUS_KEY' makes one "
                "beside a bus key of your own")
_PUBLIC_FIX = ("copy the vehicle's /etc/u2sa/pilot.pub beside this machine's bus key "
               "(ssh pi@rover cat /etc/u2sa/pilot.pub > pilot.pub), or make a pair with 'u2sa key pilot'")


def _read(path: Path, what: str, fix: str) -> bytes:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise BusKeyError(f"no {what} at {path}: {fix}") from None
    except PermissionError:
        raise BusKeyError(f"cannot read the {what} {path} (permission denied): {fix}") from None
    except OSError as exc:
        raise BusKeyError(f"cannot read the {what} {path}: {exc.strerror or exc}") from None
    return parse_key(data, source=str(path))


def public_of(seed: bytes) -> bytes:
    """The public key of the private key (seed) *seed*."""
    from nacl.signing import SigningKey

    return bytes(SigningKey(seed).verify_key)


def write_pilot_pair(bus_key_file: Path, *, system: bool = False) -> bytes:
    """Make a new pilot pair beside *bus_key_file*; the public key id.

    *system* (``u2sa install``, as root): pilot.key root:u2sa-pilot mode 0040, so only that
    group reads it (not even a uid-0 unit without CAP_DAC_OVERRIDE, as the HSM's), and
    pilot.pub 0644. Otherwise (a run's, a sim's, a test's pair) the caller's, 0600 and 0644.
    """
    private, public_path = pilot_paths(bus_key_file)
    seed = os.urandom(KEY_BYTES)
    public = public_of(seed)
    gid = _group_id(PILOT_GROUP) if system and os.geteuid() == 0 else None
    write_key_file(private, seed, mode=0o040 if gid is not None else 0o600, gid=gid)
    write_key_file(public_path, public, mode=0o644, gid=None)
    return pilot_key_id(public)


def _group_id(name: str) -> int | None:
    try:
        return grp.getgrnam(name).gr_gid
    except KeyError:
        return None

