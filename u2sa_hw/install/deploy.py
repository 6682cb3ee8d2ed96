"""``u2sa install`` / ``u2sa uninstall``: put a vehicle profile's services under systemd.

Install, on the SBC as root (or staged into ``--root DIR`` for packaging and tests):

1. creates the group u2sa, the device groups dialout, i2c, gpio and the group u2sa-pilot
   (the RC mux's unit alone; the user u2sa is not a member) where missing, and the system
   user u2sa (no login, home /var/lib/u2sa);
2. makes the venv under /opt/u2sa/venv, by default built with pip, inside DIR with ``--root``
   (see :mod:`u2sa_hw.install.system`);
3. installs the profile and service configs under /etc/u2sa (never overwriting one the
   user changed: the new default goes beside it as ``.new``) with the files the services'
   declared file settings name (a secret one root:u2sa 0640), and makes the vehicle's bus
   key /etc/u2sa/bus.key (root:u2sa 0640) unless one is there, and the pilot's pair
   /etc/u2sa/pilot.key (root:u2sa-pilot 0040: only the RC mux's unit reads it) and
   /etc/u2sa/pilot.pub (0644) unless both are there (docs/security.md);
4. makes the log directory /var/log/u2sa (u2sa:u2sa 0770) and declares it in
   /etc/tmpfiles.d/u2sa.conf, so that it exists before any unit starts;
5. installs the units, the udev rules and /etc/sysctl.d/60-u2sa-lcm.conf (LCM's
   receive buffers may grow to 4 MiB), enables ``u2sa.target`` and one
   ``u2sa@NAME.service`` per enabled service (the wants symlinks, made directly);
6. reloads systemd and udev and applies the sysctl file (not with ``--root``);
7. records all of it in /opt/u2sa/install-manifest.json.

Every step compares with what is there, so a second run changes nothing and says so.
Uninstall removes what the manifest lists; configs, logs and recordings stay unless
``--purge``, which also deletes the user and the groups that install created.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path
from typing import Callable

from u2sa_hw.bus.key import BusKeyError, ensure_key, parse_key
from u2sa_hw.bus.pilot import PILOT_GROUP, PILOT_KEY_NAME, PILOT_PUB_NAME, public_of, write_pilot_pair
from u2sa_hw.install.files import InstallTree
from u2sa_hw.install.manifest import MANAGED, MANIFEST_PATH, Manifest, host_path, load_manifest, save_manifest
from u2sa_hw.install.system import (InstallError, SERVICE_USER, apply_sysctl, apply_tmpfiles, ensure_users,
                                    group_members, owner_ids, reload_systemd, reload_udev, remove_users, user_ids)
from u2sa_hw.install.venv import VENV_MODES, ensure_venv, project_source
from u2sa_hw.install.preflight import load_for_install, offline_check, preflight
from u2sa_hw.install.referenced import installed_files, rewrites
from u2sa_hw.install.udev import VEHICLE_RULES, render_rules
from u2sa_hw.install.units import (CONFIG_DIR, DOC, ETC_DIR, HSM_LOG, HSM_STATE_DIR, LOG_DIR, LOG_DIR_MODE, PROFILE, STATE_DIR, SYSUSERS,
                                   SYSCTL, TARGET, TMPFILES, UDEV_DIR, UNIT_DIR, render_profile, service_configs,
                                   service_units, sysctl_conf, sysusers_conf, tmpfiles_conf, udev_sources,
                                   unit_dropins, unit_sources, wants_links)

OPT_DIR = "/opt/u2sa"
# Directories uninstall (without --purge) leaves, with what is in them.
KEPT_DIRS = (ETC_DIR, CONFIG_DIR, OPT_DIR, LOG_DIR)
BUS_KEY = f"{ETC_DIR}/bus.key"
PILOT_KEY = f"{ETC_DIR}/{PILOT_KEY_NAME}"   # the pilot's Ed25519 private key: root:u2sa-pilot 0040
PILOT_PUB = f"{ETC_DIR}/{PILOT_PUB_NAME}"   # its public key, which every receiver checks RC_MODE with: 0644
PILOT_KEY_MODE = 0o040   # the group u2sa-pilot reads it; not even root's own bits (the HSM runs as uid 0)


def _check_root(root: Path, *, create: bool = False) -> Path:
    """*root* resolved; refused when it is this system and we are not root; made when *create*."""
    root = root.resolve()
    if root == Path("/") and os.geteuid() != 0:
        raise InstallError("installing on this system needs root: run `sudo u2sa install ...`, "
                           "or stage into a directory with --root DIR")
    if root != Path("/") and not root.is_dir():
        if not create:
            raise InstallError(f"--root {root}: no such directory (nothing was installed there)")
        try:
            root.mkdir(parents=True)
        except OSError as exc:
            raise InstallError(f"--root {root}: cannot create it ({exc.strerror}); pick a directory you can "
                               "write to") from None
    return root


def install(*, vehicle: Path | str, root: Path | str = "/", venv: str | None = None,
            python: str | None = None, source: str | None = None, force: bool = False,
            progress: Callable[[str], None] | None = None) -> InstallTree:
    """Install (or update) the deployment of the profile *vehicle* under *root*; the tree lists the changes.

    The offline check (``u2sa check``) runs first, on the file as written. Refuses
    (InstallError listing every problem, nothing written) when it finds errors or install
    could not make a runnable vehicle of the profile, unless *force*; then what could not be
    done is in ``tree.failures`` and the check's errors in ``tree.warnings``. Not even *force*
    installs a profile that does not load or has a ``[safety]`` error.

    *venv* is ``build`` unless given, with *root* too: a staged tree gets a venv built inside it
    that boots as the image's /opt/u2sa/venv. *progress* gets pip's output line by line while it
    builds one (None: quiet).
    """
    if not vehicle:
        raise InstallError("install needs a vehicle profile: pass --vehicle FILE")
    path = Path(vehicle)
    if Path(root).resolve() == Path("/"):
        _check_root(Path(root))   # not root: refused before the check runs
    mode = venv or "build"
    if mode not in VENV_MODES:
        raise InstallError(f"--venv {mode}: use one of {', '.join(VENV_MODES)}")
    src = project_source(source)
    root_path = Path(root).resolve()
    # Everything that can be refused is checked before anything is written, the offline check first: on
    # the file as written, so a refusal has its whole list with file, key and fix ([safety] included).
    checked = offline_check(path, root=root_path)
    profile = load_for_install(path, checked)
    units = service_units(profile)
    configs_plain = service_configs(profile)
    found = preflight(profile, root=root_path, force=force, checked=checked,
                      taken={PROFILE, BUS_KEY, PILOT_KEY, PILOT_PUB, *configs_plain})
    profile_text = render_profile(profile, settings=rewrites(found.references, in_config=False))
    configs = service_configs(profile, rewrites=rewrites(found.references, in_config=True))
    vehicle_rules = render_rules(found.plan, profile=PROFILE)
    root = _check_root(Path(root), create=True)

    tree = InstallTree(root=root, old=load_manifest(root))
    tree.warnings, tree.failures = found.warnings, found.failures
    ensure_users(tree)
    owner = owner_ids(root)
    ensure_venv(tree, mode=mode, source=src, python=python, progress=progress)

    unit_files = {**unit_sources(src), **unit_dropins(profile, pwm_services=found.plan.pwm_services)}
    unit_actions = [tree.put_managed(dest, data) for dest, data in unit_files.items()]
    unit_actions += [tree.link(dest, target) for dest, target in wants_links(units).items()]
    rule_actions = [tree.put_managed(dest, data) for dest, data in udev_sources(src).items()]
    rule_actions.append(tree.put_managed(f"{UDEV_DIR}/{VEHICLE_RULES}", vehicle_rules))
    tree.put_managed(SYSUSERS, sysusers_conf())
    sysctl_action = tree.put_managed(SYSCTL, sysctl_conf())
    doc = src / "docs" / "deployment.md"
    if doc.is_file():
        tree.put_managed(DOC, doc.read_bytes())

    tree.make_dir(ETC_DIR, mode=0o755)
    # Services write their configs back (atomically, by rename) into this directory.
    tree.make_dir(CONFIG_DIR, mode=0o2770, owner=owner)
    tree.put_config(PROFILE, profile_text, mode=0o644)
    _ensure_bus_key(tree, owner=owner)
    _ensure_pilot_pair(tree)
    for dest, data in configs.items():
        tree.put_config(dest, data, mode=0o660, owner=owner)
    # Missions, objects...: the user's once installed, like the configs (one file may be named twice);
    # a token or key (a setting declared file="secret") root:u2sa 0640, never world-readable.
    for dest, (source, secret) in sorted(installed_files(found.references).items()):
        if secret:
            tree.put_secret(dest, source.read_bytes(), owner=owner)
        else:
            tree.put_config(dest, source.read_bytes(), mode=0o644)
    for item in found.plan.can_without_bitrate:
        tree.note("skipped", f"CAN {item}", "the address has no bitrate=: the interface is left as configured")
    _ensure_log_dir(tree)

    before = len(tree.changes)
    tree.prune()
    pruned = any(c.path.startswith(UNIT_DIR) for c in tree.changes[before:])
    tree.new.units_enabled = [TARGET, *(u.unit for u in units)]
    tree.new.profile_source = str(profile.path.resolve())
    reload_systemd(tree, units_changed=pruned or any(a != "unchanged" for a in unit_actions))
    reload_udev(tree, rules_changed=any(a != "unchanged" for a in rule_actions),
                can_channels=list(found.plan.can_channels))
    apply_sysctl(tree, SYSCTL, changed=sysctl_action != "unchanged")
    if save_manifest(root, tree.new) and tree.old.files == {}:
        tree.note("created", MANIFEST_PATH)
    return tree


def _ensure_bus_key(tree: InstallTree, *, owner: tuple[int, int] | None) -> None:
    """/etc/u2sa/bus.key, 256 random bits, root:u2sa 0640, unless a key is there (then only its mode is set).

    It is not in the manifest: uninstall keeps it with the configs, ``--purge`` removes /etc/u2sa.
    """
    path = tree.path(BUS_KEY)
    try:
        made = ensure_key(path, group=None)
        if owner is not None:
            os.chown(path, *owner)
        os.chmod(path, 0o640 if owner is not None else 0o600)
    except (BusKeyError, OSError) as exc:
        raise InstallError(f"{BUS_KEY}: {exc}") from None
    if made:
        tree.note("created", BUS_KEY, "the vehicle's bus key; copy it to a ground station with 'u2sa key show'")
    else:
        tree.note("unchanged", BUS_KEY, "the existing bus key is kept")


def _ensure_pilot_pair(tree: InstallTree) -> None:
    """/etc/u2sa/pilot.key root:u2sa-pilot 0040 and pilot.pub root:root 0644, made unless both are there.

    The private key signs RC_MODE and MANUAL_CMD; only the RC mux's unit has the group u2sa-pilot
    (32-pilot-key.conf), the user u2sa is not in it, and the owner root has no bit, so not even the
    HSM (uid 0 without CAP_DAC_OVERRIDE) reads it. The group id is the tree's (``--root``: its
    etc/group), set here after writing, whatever the host's group database says; a tree without
    the group (no etc/group yet) gets 0600. A pair that is there is kept (a second install, one
    after ``u2sa key pilot``), its owner and mode put back; a pilot.pub that went missing is made
    again from pilot.key, so laptops holding it keep checking. Like the bus key, not in the
    manifest: uninstall keeps both with the configs, ``--purge`` removes /etc/u2sa.
    """
    private, public = tree.path(PILOT_KEY), tree.path(PILOT_PUB)
    owner = owner_ids(tree.root, PILOT_GROUP)
    mode = PILOT_KEY_MODE if owner is not None else 0o600
    how = (f"root:{PILOT_GROUP} {mode:04o}" if owner is not None
           else f"root:root {mode:04o} (no group {PILOT_GROUP} yet)")
    try:
        for path in (private, public):
            if path.is_symlink():
                raise BusKeyError(f"{path} is a symbolic link; put the file itself there (or remove it: install "
                                  "makes a new pair)")
        if private.is_file() and public.is_file():
            made = None
        elif private.is_file():
            made = "pub"
            _write_public(public, public_of(parse_key(private.read_bytes(), source=str(private))))
        else:
            made = "pair"
            write_pilot_pair(tree.path(BUS_KEY), system=True)
        fixed_key = _set_owner_mode(private, owner or (0, 0), mode)
        fixed_pub = _set_owner_mode(public, (0, 0), 0o644)
    except (BusKeyError, OSError) as exc:
        raise InstallError(f"{PILOT_KEY}: {exc}") from None
    if made == "pair":
        tree.note("created", PILOT_KEY, f"the pilot's private key, {how}: only the RC mux's unit reads it")
        tree.note("created", PILOT_PUB, "the pilot's public key; copy it beside a laptop's bus key to check RC_MODE")
    else:
        tree.note("updated" if fixed_key else "unchanged", PILOT_KEY,
                  f"the existing pilot key is kept; owner and mode {how} again" if fixed_key
                  else "the existing pilot key is kept")
        tree.note("created" if made == "pub" else "updated" if fixed_pub else "unchanged", PILOT_PUB,
                  "made again from the existing pilot.key" if made == "pub"
                  else "owner and mode root:root 0644 again" if fixed_pub else "")
    if SERVICE_USER in group_members(tree.root, PILOT_GROUP):
        tree.warnings.append(f"{host_path(tree.root, '/etc/group')}: the user {SERVICE_USER} is in the group "
                             f"{PILOT_GROUP}, so every service could read {PILOT_KEY} and sign as the pilot; fix: "
                             f"sudo gpasswd -d {SERVICE_USER} {PILOT_GROUP} (only the RC mux's unit gets the group, "
                             "from its drop-in 32-pilot-key.conf)")


def _write_public(path: Path, public: bytes) -> None:
    from u2sa_hw.install.manifest import atomic_write

    atomic_write(path, public.hex().encode() + b"\n", mode=0o644)


def _set_owner_mode(path: Path, owner: tuple[int, int], mode: int) -> bool:
    """Give *path* *owner* and *mode* (the mode first when it narrows, so the file is never more open); True
    when either changed."""
    st = path.lstat()
    changed = False
    if st.st_mode & 0o7777 != mode:
        os.chmod(path, mode & st.st_mode & 0o7777)   # narrow first: never readable by the new owner and the old
        changed = True
    if (st.st_uid, st.st_gid) != owner:
        os.chown(path, *owner, follow_symlinks=False)
        changed = True
    if changed:
        os.chmod(path, mode)
    return changed


def _ensure_log_dir(tree: InstallTree) -> None:
    """/var/log/u2sa, u2sa:u2sa 0770, before any unit starts: the services and the HSM share it."""
    actions = [tree.put_managed(TMPFILES, tmpfiles_conf())]
    log_owner = user_ids(tree.root)
    if log_owner is None:
        tree.note("skipped", LOG_DIR, f"no user {SERVICE_USER} in {tree.root}/etc/passwd yet; "
                  f"systemd-tmpfiles makes it at boot from {TMPFILES}")
    else:
        actions.append(tree.make_dir(LOG_DIR, mode=LOG_DIR_MODE, owner=log_owner))
        _reclaim_hsm_log(tree, gid=log_owner[1])
    apply_tmpfiles(tree, TMPFILES, changed=any(a != "unchanged" for a in actions))


def _reclaim_hsm_log(tree: InstallTree, *, gid: int) -> None:
    """Give back to root:u2sa an hsm.log that systemd chowned to u2sa under an earlier install.

    Then the HSM shared the services' LogsDirectory=, so a service's start left hsm.log
    u2sa's, 0640, and the HSM (uid 0 without CAP_DAC_OVERRIDE) could not append to it.
    (Not a tmpfiles ``z`` line: systemd-tmpfiles refuses a root-owned file in a directory
    of u2sa as an unsafe path transition.)
    """
    path = tree.path(HSM_LOG)
    if path.is_symlink() or not path.is_file():
        return
    st = path.lstat()
    if (st.st_uid, st.st_gid) != (0, gid):
        os.chown(path, 0, gid, follow_symlinks=False)
        tree.note("updated", HSM_LOG, "owner root:u2sa again, so the HSM can append to it")


def _stop_units(tree: InstallTree) -> None:
    if tree.root != Path("/") or not Path("/run/systemd/system").is_dir():
        return
    units = [u for u in tree.old.units_enabled if u != TARGET]
    done = subprocess.run(["systemctl", "stop", TARGET, *units], capture_output=True, text=True, timeout=120)
    if done.returncode != 0:
        raise InstallError(f"systemctl stop {TARGET} failed: {done.stderr.strip()}; stop the services, then "
                           "uninstall again")
    tree.note("updated", TARGET, "stopped with its services")


def uninstall(*, root: Path | str = "/", purge: bool = False) -> InstallTree:
    """Remove what install put under *root* (configs, logs and data too when *purge*)."""
    root = _check_root(Path(root))
    old = load_manifest(root)
    if old is None or (not purge and not any(r.kind == MANAGED for r in old.files.values())
                       and not old.symlinks and not old.venv):
        raise InstallError(f"nothing to uninstall under {root}: no install recorded in "
                           f"{host_path(root, MANIFEST_PATH)} (what an earlier uninstall kept goes with --purge)")
    tree = InstallTree(root=root, old=old)
    _stop_units(tree)
    if old.venv.get("path"):
        tree.remove_tree(old.venv["path"])
    tree.remove_installed(purge=purge, keep_dirs=() if purge else (LOG_DIR,))
    if purge:
        host_path(root, MANIFEST_PATH).unlink(missing_ok=True)
        tree.note("removed", MANIFEST_PATH)
        for directory in (ETC_DIR, LOG_DIR, STATE_DIR, HSM_STATE_DIR):
            tree.remove_tree(directory)
        remove_users(tree)
        tree.remove_empty_dirs()
    else:
        # What stays (configs, the user and groups) stays on record: a later install still
        # knows which configs the user changed, and a later --purge what install created.
        kept = Manifest(files={p: r for p, r in old.files.items() if r.kind != MANAGED},
                        users=old.users, groups=old.groups, profile_source=old.profile_source,
                        dirs=[d for d in old.dirs if any(d == k or k.startswith(d + "/") for k in KEPT_DIRS)])
        if save_manifest(root, kept):
            tree.note("updated", MANIFEST_PATH, "now lists only what uninstall kept")
    reload_systemd(tree, units_changed=True)
    reload_udev(tree, rules_changed=True)
    return tree
