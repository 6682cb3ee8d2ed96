"""Writing the installed tree: files, configs, symlinks and directories, idempotently.

:class:`InstallTree` writes under a root (``/`` on the vehicle, a staging directory with
``--root``) and reports every change; writing what is already there is "unchanged", so
a second install reports nothing. Managed files (units, rules) are replaced when they
differ. Config files are the user's once installed: one whose content differs from the
checksum recorded at install time was changed by the user and is never overwritten; a
changed default is written beside it as ``NAME.new``. A file holding a secret (a setting declared
``file="secret"``) is written like a config but ``root:u2sa`` 0640 (:meth:`InstallTree.put_secret`).
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from u2sa_hw.install.manifest import (CONFIG, CONFIG_NEW, MANAGED, FileRecord, Manifest, atomic_write,
                                      host_path, sha256_bytes, sha256_file)

Owner = tuple[int, int] | None

SECRET_MODE = 0o640   # root:u2sa: the services (group u2sa) read it, nobody else does

# Actions that change the system; "unchanged" and "kept" do not.
CHANGING = frozenset({"created", "updated", "removed"})


@dataclass(frozen=True)
class Change:
    """One thing install or uninstall did (or found already done) to a vehicle path."""

    action: str  # created, updated, removed, unchanged, kept, skipped
    path: str
    note: str = ""

    def __str__(self) -> str:
        note = f"  ({self.note})" if self.note else ""
        return f"{self.action:9} {self.path}{note}"


class InstallTree:
    """Files under *root*, compared against the previous manifest *old*; builds the new one."""

    def __init__(self, *, root: Path, old: Manifest | None) -> None:
        self.root = root
        self.old = old or Manifest()
        self.new = Manifest()
        self.changes: list[Change] = []
        self.warnings: list[str] = []   # said and gone past (the check's errors under --force)
        self.failures: list[str] = []   # asked for by the profile, not done: install exits 1

    @property
    def changed(self) -> bool:
        """True when anything was created, updated or removed."""
        return any(c.action in CHANGING for c in self.changes)

    def note(self, action: str, path: str, note: str = "") -> None:
        """Record a change that was made elsewhere (users, venv, reloads)."""
        self.changes.append(Change(action, path, note))

    def path(self, vehicle_path: str) -> Path:
        """The host path of *vehicle_path* under the root."""
        return host_path(self.root, vehicle_path)

    def _apply_mode(self, path: Path, mode: int, owner: Owner) -> bool:
        st = path.lstat()
        changed = False
        if owner is not None and (st.st_uid, st.st_gid) != owner:
            os.chown(path, *owner)
            changed = True
        if st.st_mode & 0o7777 != mode:
            os.chmod(path, mode)
            changed = True
        return changed

    def put_managed(self, dest: str, data: bytes, *, mode: int = 0o644, owner: Owner = None) -> str:
        """Install a file that install owns; replace it when it differs. Returns the action."""
        self.ensure_parents(dest)
        path = self.path(dest)
        current = sha256_file(path)
        new_sha = sha256_bytes(data)
        self.new.files[dest] = FileRecord(MANAGED, new_sha)
        if current == new_sha:
            action = "updated" if self._apply_mode(path, mode, owner) else "unchanged"
            self.changes.append(Change(action, dest, "mode/owner" if action == "updated" else ""))
            return action
        recorded = self.old.files.get(dest)
        note = ""
        if current is not None and recorded is not None and current != recorded.sha256:
            note = "was edited after install; replaced (put local changes in a drop-in or a separate file)"
        atomic_write(path, data, mode=mode)
        self._apply_mode(path, mode, owner)
        action = "created" if current is None else "updated"
        self.changes.append(Change(action, dest, note))
        return action

    def put_config(self, dest: str, data: bytes, *, mode: int = 0o640, owner: Owner = None) -> str:
        """Install a config file without ever overwriting one the user changed (then ``dest.new``)."""
        self.ensure_parents(dest)
        path = self.path(dest)
        current = sha256_file(path)
        new_sha = sha256_bytes(data)
        recorded = self.old.files.get(dest)
        new_path = f"{dest}.new"
        if current is None or current == new_sha or (recorded is not None and recorded.sha256 == current):
            self.new.files[dest] = FileRecord(CONFIG, new_sha)
            if current == new_sha:
                self._apply_mode(path, mode, owner)
                self.changes.append(Change("unchanged", dest))
                action = "unchanged"
            else:
                atomic_write(path, data, mode=mode)
                self._apply_mode(path, mode, owner)
                action = "created" if current is None else "updated"
                note = "" if current is None else "new default; you had not changed it"
                self.changes.append(Change(action, dest, note))
            old_new = self.old.files.get(new_path)
            if old_new is not None and old_new.kind == CONFIG_NEW:
                self._remove_file(new_path, "the config now matches it")
            return action
        # Changed by the user (or there before install): keep it, offer the default beside it.
        self.new.files[dest] = FileRecord(CONFIG, recorded.sha256 if recorded else "")
        self.changes.append(Change("kept", dest, f"changed since install; the current default is in {new_path}"))
        if sha256_file(self.path(new_path)) == new_sha:
            self.new.files[new_path] = FileRecord(CONFIG_NEW, new_sha)
            self.changes.append(Change("unchanged", new_path))
            return "kept"
        atomic_write(self.path(new_path), data, mode=mode)
        self._apply_mode(self.path(new_path), mode, owner)
        self.new.files[new_path] = FileRecord(CONFIG_NEW, new_sha)
        self.changes.append(Change("created", new_path, f"new default for your changed {dest}"))
        return "kept"

    def put_secret(self, dest: str, data: bytes, *, owner: Owner) -> str:
        """Install a file holding a secret (a token, a private key) like a config, readable only by root and
        the group u2sa: ``root:u2sa`` mode 0640 when *owner* (root, the gid of u2sa) is known, else 0600.

        Fail-safe: the mode is set on the temp file before it takes the name (never readable by others,
        not even for a moment), and put back on a copy the user changed since install (kept, not rewritten),
        as install does for the bus key.
        """
        mode = SECRET_MODE if owner is not None else 0o600
        action = self.put_config(dest, data, mode=mode, owner=owner)
        if action == "kept" and self._apply_mode(self.path(dest), mode, owner):
            self.changes.append(Change("updated", dest, f"a secret: mode {mode:04o} again"))
        return action

    def link(self, dest: str, target: str) -> str:
        """Make *dest* a symlink to *target* (a vehicle path, not rooted: it resolves on the vehicle)."""
        self.ensure_parents(dest)
        path = self.path(dest)
        self.new.symlinks[dest] = target
        if path.is_symlink() and os.readlink(path) == target:
            self.changes.append(Change("unchanged", dest))
            return "unchanged"
        existed = path.is_symlink() or path.exists()
        if existed:
            path.unlink()
        path.symlink_to(target)
        action = "updated" if existed else "created"
        self.changes.append(Change(action, dest, f"-> {target}"))
        return action

    def ensure_parents(self, dest: str) -> None:
        """Create the missing directories above *dest* (mode 0755), recording those install made."""
        parts = Path(dest).parent.parts
        for i in range(2, len(parts) + 1):
            vpath = str(Path(*parts[:i]))
            path = self.path(vpath)
            if path.is_dir():
                if vpath in self.old.dirs and vpath not in self.new.dirs:
                    self.new.dirs.append(vpath)
                continue
            path.mkdir(mode=0o755)
            self.new.dirs.append(vpath)
            self.changes.append(Change("created", vpath))

    def make_dir(self, dest: str, *, mode: int = 0o755, owner: Owner = None) -> str:
        """Create directory *dest* (and record it when install made it) with *mode* and *owner*."""
        path = self.path(dest)
        self.ensure_parents(dest)
        if path.is_dir():
            if dest in self.old.dirs and dest not in self.new.dirs:
                self.new.dirs.append(dest)
            action = "updated" if self._apply_mode(path, mode, owner) else "unchanged"
            self.changes.append(Change(action, dest, "mode/owner" if action == "updated" else ""))
            return action
        path.mkdir()
        self._apply_mode(path, mode, owner)
        self.new.dirs.append(dest)
        self.changes.append(Change("created", dest))
        return "created"

    def _remove_file(self, dest: str, note: str = "") -> None:
        path = self.path(dest)
        if path.is_symlink() or path.exists():
            path.unlink()
            self.changes.append(Change("removed", dest, note))

    def prune(self) -> None:
        """Remove managed files and symlinks the previous install made that this one did not."""
        for dest, rec in self.old.files.items():
            if dest not in self.new.files and rec.kind in (MANAGED, CONFIG_NEW):
                self._remove_file(dest, "no longer installed")
        for dest in self.old.symlinks:
            if dest not in self.new.symlinks:
                self._remove_file(dest, "no longer enabled")
        # e.g. u2sa@NAME.service.d of a service renamed or dropped: install made it, nothing needs it now.
        for dest in sorted(set(self.old.dirs) - set(self.new.dirs), key=len, reverse=True):
            path = self.path(dest)
            if path.is_dir() and not path.is_symlink() and not any(path.iterdir()):
                path.rmdir()
                self.changes.append(Change("removed", dest, "no longer needed"))

    def remove_installed(self, *, purge: bool, keep_dirs: tuple[str, ...] = ()) -> None:
        """Uninstall: remove what the old manifest lists (configs only when *purge*), then its empty dirs
        other than *keep_dirs*."""
        for dest, rec in sorted(self.old.files.items()):
            if rec.kind == MANAGED or purge:
                self._remove_file(dest)
            else:
                self.changes.append(Change("kept", dest, "config (u2sa uninstall --purge removes it)"))
        for dest in sorted(self.old.symlinks):
            self._remove_file(dest)
        self.remove_empty_dirs(keep=keep_dirs)

    def remove_empty_dirs(self, *, keep: tuple[str, ...] = ()) -> None:
        """Remove the directories install created (old manifest) that are now empty, deepest first."""
        for dest in sorted(self.old.dirs, key=len, reverse=True):
            if any(dest == k or k.startswith(dest + "/") for k in keep):
                continue
            path = self.path(dest)
            if path.is_dir() and not path.is_symlink() and not any(path.iterdir()):
                path.rmdir()
                self.changes.append(Change("removed", dest))

    def remove_tree(self, dest: str) -> None:
        """Remove the directory tree *dest* if it exists (venv, purged data)."""
        path = self.path(dest)
        if path.is_symlink():
            path.unlink()
            self.changes.append(Change("removed", dest))
        elif path.is_dir():
            shutil.rmtree(path)
            self.changes.append(Change("removed", dest))
