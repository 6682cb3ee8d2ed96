"""A real systemd as PID 1 of a private PID, mount, cgroup, UTS and IPC namespace (DESIGN.md 9).

Reusable by every test (and bench script) that needs units under systemd:

    root = stage_root(tmp_path / "root")          # a copy of /etc, empty unit dir, var/
    u2sa install --vehicle ... --root root        # stage our units into it
    with SystemdNamespace(root, unit="u2sa.target") as ns:
        ns.wait_active("u2sa@estimator.service")
        os.kill(ns.host_pid(ns.main_pid("u2sa@estimator.service")), signal.SIGKILL)

Inside the namespace the staged ``etc``, ``opt`` and ``var`` are bind-mounted over
/etc, /opt and /var; /run, /tmp and /var/tmp are fresh tmpfs; cgroup2 is mounted on a
cgroup of its own; systemd loads units only from the staged /etc/systemd/system (plus
the few targets it needs, copied from the host, and journald on its /run socket, so
``ns.journal("-u", UNIT)`` reads the units' output and systemd's own messages), runs in container mode
(``container=``: no remounts, no global sysctl writes at shutdown) and boots straight
into ``--unit=``. Nothing of the host's unit set is ever started, and the host's /tmp
is never touched. The network namespace is the host's, so LCM multicast between a test
and the services works (``private_network=True`` gives it one with only lo instead).
``poweroff()`` (also on exit) stops everything cleanly and the namespace disappears with
its PID 1.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import time
import uuid
from pathlib import Path
from typing import Callable

from staged_code import code_hidden, stage_code

SYSTEMD = Path("/lib/systemd/systemd")
SUPPORT_DIR = "etc/systemd/u2sa-test-support"
# What systemd needs beyond our units to boot into a target and power off cleanly.
SUPPORT_UNITS = ("basic.target", "sysinit.target", "multi-user.target", "network.target", "shutdown.target",
                 "umount.target", "final.target", "poweroff.target", "systemd-poweroff.service",
                 "systemd-journald.socket")
# journald, so that the units' output and systemd's own record of them ("Watchdog timeout",
# "Failed with result") are in a journal the tests read (journalctl inside the namespace,
# volatile in its /run). Started through sysinit.target, which every unit with default
# dependencies requires. Only its /run socket: not the /dev/log one (its Symlinks= would
# replace the host's /dev/log, since /dev is shared) nor the audit one.
JOURNALD = "systemd-journald.service"
JOURNALD_SOCKETS = "Sockets=systemd-journald.socket"


def cannot_boot_reason() -> str | None:
    """Why systemd cannot be booted in a namespace here, or None when it can."""
    if os.geteuid() != 0:
        return "booting systemd in a namespace needs root"
    for tool in ("unshare", "nsenter", "systemctl"):
        if shutil.which(tool) is None:
            return f"{tool} is not installed"
    if not SYSTEMD.exists():
        return f"{SYSTEMD} is not installed"
    if cgroup2_mount() is None:
        return "no cgroup2 (unified) hierarchy is mounted"
    return interpreter_hidden_reason()


def interpreter_hidden_reason() -> str | None:
    """Why no shared venv the sandboxed services can run could be made here, or None.

    A checkout or venv that the units' PrivateTmp=/ProtectHome= hide is staged into the
    root (tests/staged_code.py); only the interpreter must be one they can reach."""
    from u2sa_hw.install.system import InstallError
    from u2sa_hw.install.venv import choose_python

    try:
        choose_python(None)
    except InstallError as exc:
        return str(exc)
    return None


def cgroup2_mount() -> Path | None:
    """Where the cgroup2 hierarchy is mounted on the host."""
    for line in Path("/proc/self/mountinfo").read_text().splitlines():
        left, _, right = line.partition(" - ")
        if right.split(" ")[0] == "cgroup2":
            return Path(left.split(" ")[4])
    return None


def stage_root(root: Path, *, code: bool = True) -> Path:
    """Prepare *root* for install --root and a boot: a copy of the host's /etc (users,
    libraries' config) without any unit, an empty var/ tree, and the support units; and,
    when *code* and the units could not see this checkout or its venv (under /tmp or a
    home), the code staged into its /opt (``staged_code.stage_code``: run install with
    ``u2sa_command(root)``, and ``u2sa_inside(root)`` in the namespace). ``code=False``:
    never, for a root whose venv ``u2sa install --venv build`` builds inside it."""
    root.mkdir(parents=True, exist_ok=True)
    subprocess.run(["cp", "-a", "/etc", str(root / "etc")], check=True)
    units = root / "etc/systemd/system"
    shutil.rmtree(units, ignore_errors=True)
    units.mkdir(parents=True)
    for gone in ("etc/u2sa", "etc/udev/rules.d"):
        shutil.rmtree(root / gone, ignore_errors=True)
    # The staged vehicle shares the test session's bus key, as a vehicle shares its key with
    # its ground station; install keeps a key that is there (and sets it to root:u2sa 0640).
    session_key = os.environ.get("U2SA_BUS_KEY_FILE")
    if session_key:
        (root / "etc/u2sa").mkdir(parents=True)
        shutil.copy(session_key, root / "etc/u2sa/bus.key")
    support = root / SUPPORT_DIR
    support.mkdir(parents=True)
    for name in SUPPORT_UNITS:
        shutil.copy(Path("/lib/systemd/system") / name, support / name)
    journald = (Path("/lib/systemd/system") / JOURNALD).read_text()
    (support / JOURNALD).write_text("\n".join(JOURNALD_SOCKETS if line.startswith("Sockets=") else line
                                              for line in journald.splitlines()) + "\n")
    (support / "sysinit.target.wants").mkdir()
    (support / "sysinit.target.wants" / JOURNALD).symlink_to(f"../{JOURNALD}")
    for d in ("opt", "var/lib", "var/log", "var/tmp", "var/cache"):
        (root / d).mkdir(parents=True, exist_ok=True)
    (root / "var/run").symlink_to("/run")
    (root / "var/lock").symlink_to("/run/lock")
    if code and code_hidden():
        stage_code(root)
    return root


BOOT_SCRIPT = """\
set -e
mount --bind "$R/etc" /etc
mount --bind "$R/opt" /opt
mount --bind "$R/var" /var
umount -R /sys/fs/cgroup 2>/dev/null || true
mount -t cgroup2 cgroup2 /sys/fs/cgroup
mount -t tmpfs -o mode=0755 tmpfs /run
mount -t tmpfs -o mode=1777 tmpfs /tmp
mount -t tmpfs -o mode=1777 tmpfs /var/tmp
export SYSTEMD_UNIT_PATH=/etc/systemd/system:/{support}
export container=u2sa-test
exec {systemd} --system --unit="$UNIT" --show-status=no </dev/null >/dev/null 2>&1
"""

OUTER_SCRIPT = """\
set -e
mkdir "$CG"
echo $$ > "$CG/cgroup.procs"
exec unshare --pid --fork --mount-proc --mount --uts --ipc --cgroup $NET --propagation private sh -c "$BOOT"
"""


class SystemdNamespace:
    """systemd booted into *unit* on the staged *root* (see the module docstring)."""

    def __init__(self, root: Path, *, unit: str = "u2sa.target", boot_timeout: float = 30.0,
                 private_network: bool = False) -> None:
        self.root = root.resolve()
        self.private_network = private_network  # a network namespace with only lo: a vehicle offline
        self.unit = unit
        self.boot_timeout = boot_timeout
        mount = cgroup2_mount()
        if mount is None:
            raise RuntimeError("no cgroup2 hierarchy mounted")
        own = next(line[3:] for line in Path("/proc/self/cgroup").read_text().splitlines() if line.startswith("0::"))
        self.cgroup = mount / own.lstrip("/") / f"u2sa-ns-{uuid.uuid4().hex[:8]}"
        self.proc: subprocess.Popen[bytes] | None = None
        self.pid = 0  # systemd's PID on the host

    # -- lifecycle -------------------------------------------------------------------------
    def boot(self) -> None:
        """Start systemd and wait until it answers and *unit* has been started."""
        env = {**os.environ, "R": str(self.root), "UNIT": self.unit, "CG": str(self.cgroup),
               "NET": "--net" if self.private_network else "",
               "BOOT": BOOT_SCRIPT.format(support=SUPPORT_DIR, systemd=SYSTEMD)}
        self.proc = subprocess.Popen(["sh", "-c", OUTER_SCRIPT], env=env, stdin=subprocess.DEVNULL,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
        if not wait_until(self._find_systemd, timeout=self.boot_timeout):
            self.kill()
            raise RuntimeError(f"systemd did not start in the namespace: {self._output()}")
        if not wait_until(lambda: self.systemctl("is-system-running", check=False).stdout.strip()
                          in ("running", "degraded"), timeout=self.boot_timeout):
            state = self.systemctl("is-system-running", check=False).stdout.strip()
            self.poweroff()
            raise RuntimeError(f"systemd in the namespace did not finish booting (state {state!r})")

    def _find_systemd(self) -> bool:
        if self.proc is None or self.proc.poll() is not None:
            raise RuntimeError(f"the namespace exited early: {self._output()}")
        children = Path(f"/proc/{self.proc.pid}/task/{self.proc.pid}/children")
        try:
            for pid in children.read_text().split():
                if Path(f"/proc/{pid}/exe").resolve().name == "systemd":
                    self.pid = int(pid)
                    return Path(f"/proc/{pid}/root/run/systemd/private").exists()
        except (FileNotFoundError, ProcessLookupError):
            pass
        return False

    def _output(self) -> str:
        if self.proc is None or self.proc.stdout is None or self.proc.poll() is None:
            return "(still running)"
        return self.proc.stdout.read().decode(errors="replace").strip()[-2000:]

    def poweroff(self, timeout: float = 30.0) -> None:
        """``systemctl poweroff`` inside; wait for the namespace to end (SIGKILL after *timeout*)."""
        if self.proc is None:
            return
        if self.proc.poll() is None:
            self.systemctl("poweroff", "--no-block", check=False)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.kill()
        self._remove_cgroup()

    def kill(self) -> None:
        """End the namespace at once: SIGKILL its PID 1 (everything inside dies with it)."""
        if self.pid:
            try:
                os.kill(self.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        if self.proc is not None:
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)
        self._remove_cgroup()

    def _remove_cgroup(self) -> None:
        if not self.cgroup.exists():
            return
        for path in sorted((p for p in self.cgroup.rglob("*") if p.is_dir()), key=lambda p: len(p.parts),
                           reverse=True) + [self.cgroup]:
            try:
                path.rmdir()
            except OSError:
                pass

    @property
    def alive(self) -> bool:
        """True while the namespace's PID 1 runs."""
        return self.proc is not None and self.proc.poll() is None

    def __enter__(self) -> "SystemdNamespace":
        self.boot()
        return self

    def __exit__(self, *exc: object) -> None:
        self.poweroff()

    # -- talking to it ---------------------------------------------------------------------
    def run(self, *cmd: str, check: bool = True, timeout: float = 30.0) -> subprocess.CompletedProcess[str]:
        """Run *cmd* inside the namespace's mount and PID (and private network) namespaces."""
        spaces = ["-m", "-p", *(["-n"] if self.private_network else [])]
        # Inside, u2sa finds the key where the vehicle's services do (/etc/u2sa/bus.key), not
        # at the session's path in the host's /tmp, which the namespace does not see.
        env = {k: v for k, v in os.environ.items() if k != "U2SA_BUS_KEY_FILE"}
        return subprocess.run(["nsenter", "-t", str(self.pid), *spaces, *cmd], capture_output=True,
                              text=True, timeout=timeout, check=check, env=env)

    def systemctl(self, *args: str, check: bool = True, timeout: float = 30.0) -> subprocess.CompletedProcess[str]:
        """``systemctl ARGS`` against the namespace's systemd."""
        return self.run("systemctl", "--no-pager", *args, check=check, timeout=timeout)

    def show(self, unit: str, *props: str) -> dict[str, str]:
        """Properties of *unit* (``systemctl show``)."""
        out = self.systemctl("show", unit, f"--property={','.join(props)}", check=False).stdout
        return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)

    def state(self, unit: str) -> str:
        """``ActiveState/SubState`` of *unit*."""
        p = self.show(unit, "ActiveState", "SubState")
        return f"{p.get('ActiveState')}/{p.get('SubState')}"

    def main_pid(self, unit: str) -> int:
        """The unit's main PID as the namespace numbers it (0 when none)."""
        return int(self.show(unit, "MainPID").get("MainPID", "0") or 0)

    def wait_active(self, unit: str, *, timeout: float = 30.0, not_pid: int = 0) -> int:
        """Wait until *unit* is active/running with a main PID other than *not_pid*; return that PID."""
        found: list[int] = []

        def ready() -> bool:
            p = self.show(unit, "ActiveState", "SubState", "MainPID")
            pid = int(p.get("MainPID", "0") or 0)
            if p.get("ActiveState") == "active" and p.get("SubState") == "running" and pid and pid != not_pid:
                found.append(pid)
                return True
            return False

        if not wait_until(ready, timeout=timeout):
            raise AssertionError(f"{unit} not active/running within {timeout} s: {self.state(unit)}; "
                                 f"{self.journal_hint(unit)}")
        return found[-1]

    def journal(self, *args: str) -> str:
        """``journalctl --no-pager -o cat ARGS`` inside the namespace (e.g. ``-u UNIT``): the text."""
        return self.run("journalctl", "--no-pager", "-o", "cat", *args, check=False).stdout

    def journal_hint(self, unit: str) -> str:
        """The unit's last result and status line and its last journal lines, for failure messages."""
        p = self.show(unit, "Result", "StatusText", "NRestarts", "ExecMainStatus")
        tail = self.journal("-u", unit, "-n", "8").strip().replace("\n", " | ")
        return ", ".join(f"{k}={v}" for k, v in p.items()) + (f"; journal: {tail}" if tail else "")

    def host_pid(self, ns_pid: int) -> int:
        """The host PID of the process the namespace calls *ns_pid*."""
        my_ns = os.readlink(f"/proc/{self.pid}/ns/pid")
        for status in Path("/proc").glob("[0-9]*/status"):
            try:
                for line in status.read_text().splitlines():
                    if line.startswith("NSpid:"):
                        ids = line.split()[1:]
                        if len(ids) >= 2 and int(ids[-1]) == ns_pid and \
                                os.readlink(f"/proc/{ids[0]}/ns/pid") == my_ns:
                            return int(ids[0])
            except (FileNotFoundError, ProcessLookupError, PermissionError):
                continue
        raise LookupError(f"no process {ns_pid} in the namespace of systemd {self.pid}")


def wait_until(predicate: Callable[[], bool], *, timeout: float, interval: float = 0.1) -> bool:
    """Poll *predicate* until it is true or *timeout* passes; its last value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(interval)
    return bool(predicate())
