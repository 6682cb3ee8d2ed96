"""What ``u2sa install`` put on the vehicle, so that it can be updated and removed.

The manifest (``/opt/u2sa/install-manifest.json``, root-owned: the services cannot
write it) records every file with the SHA-256 of the content install wrote, every
symlink, the users and groups install created (not those that were there before),
and the venv. "Changed by the user" is then decidable: a file whose content differs
from the recorded checksum was edited after install. Paths are vehicle paths
(``/etc/u2sa/vehicle.toml``), also when install staged into ``--root DIR``.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

MANIFEST_PATH = "/opt/u2sa/install-manifest.json"
FORMAT_VERSION = 1

MANAGED = "managed"      # ours: replaced on install, removed on uninstall
CONFIG = "config"        # the user's once installed: never overwritten if changed, kept on uninstall
CONFIG_NEW = "config-new"  # a newer default written beside a changed config (X.new)


def sha256_bytes(data: bytes) -> str:
    """Hex SHA-256 of *data*."""
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: Path) -> str | None:
    """Hex SHA-256 of the file at *path*, or None when there is no such file."""
    try:
        return sha256_bytes(path.read_bytes())
    except FileNotFoundError:
        return None


@dataclass
class FileRecord:
    """One installed file: its kind (managed, config, config-new) and the checksum install wrote."""

    kind: str
    sha256: str


@dataclass
class Manifest:
    """The record of one installation (see the module docstring)."""

    files: dict[str, FileRecord] = field(default_factory=dict)
    symlinks: dict[str, str] = field(default_factory=dict)
    dirs: list[str] = field(default_factory=list)
    users: list[str] = field(default_factory=list)
    groups: list[str] = field(default_factory=list)
    venv: dict[str, str] = field(default_factory=dict)
    units_enabled: list[str] = field(default_factory=list)
    profile_source: str = ""

    def to_json(self) -> str:
        """The manifest as JSON text (sorted, stable: a rewrite of the same state is byte-identical)."""
        data: dict[str, Any] = {
            "format": FORMAT_VERSION,
            "profile_source": self.profile_source,
            "files": {p: {"kind": r.kind, "sha256": r.sha256} for p, r in sorted(self.files.items())},
            "symlinks": dict(sorted(self.symlinks.items())),
            "dirs": sorted(set(self.dirs)),
            "users": sorted(set(self.users)),
            "groups": sorted(set(self.groups)),
            "venv": dict(sorted(self.venv.items())),
            "units_enabled": sorted(set(self.units_enabled)),
        }
        return json.dumps(data, indent=2) + "\n"

    @classmethod
    def from_json(cls, text: str, *, where: str) -> "Manifest":
        """Parse manifest text; ValueError names *where* and the fix when it is not a manifest."""
        try:
            data = json.loads(text)
            if data.get("format") != FORMAT_VERSION:
                raise ValueError(f"format {data.get('format')!r}, expected {FORMAT_VERSION}")
            return cls(
                files={p: FileRecord(kind=r["kind"], sha256=r["sha256"]) for p, r in data["files"].items()},
                symlinks=dict(data["symlinks"]), dirs=list(data["dirs"]), users=list(data["users"]),
                groups=list(data["groups"]), venv=dict(data["venv"]),
                units_enabled=list(data["units_enabled"]), profile_source=str(data.get("profile_source", "")))
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise ValueError(f"{where}: not a u2sa install manifest ({exc}); move it away and run "
                             "u2sa install again") from None


def host_path(root: Path, vehicle_path: str) -> Path:
    """Where the vehicle path *vehicle_path* lives under *root* (``/`` or a staging directory)."""
    return root / vehicle_path.lstrip("/")


def load_manifest(root: Path) -> Manifest | None:
    """The manifest of the installation under *root*, or None when nothing is installed there."""
    path = host_path(root, MANIFEST_PATH)
    try:
        return Manifest.from_json(path.read_text(), where=str(path))
    except FileNotFoundError:
        return None


def atomic_write(path: Path, data: bytes, *, mode: int) -> None:
    """Write *data* to *path* through a temp file in the same directory, fsync and rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def save_manifest(root: Path, manifest: Manifest) -> bool:
    """Write *manifest* under *root*; False when the file already held exactly this."""
    path = host_path(root, MANIFEST_PATH)
    text = manifest.to_json().encode()
    try:
        if path.read_bytes() == text:
            return False
    except FileNotFoundError:
        pass
    atomic_write(path, text, mode=0o644)
    return True
