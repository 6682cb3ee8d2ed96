"""The pilot's private key under a real systemd: only the RC mux's unit reads it (tests/systemd_ns.py).

`u2sa install --root` stages a vehicle with an estimator, an RC mux and the HSM; each of the
three units runs, in its installed sandbox (user, groups, drop-ins), a probe instead of its
service: the project's own code reading /etc/u2sa/pilot.key (``read_signer``), signing, and
checking the signature with pilot.pub. The RC mux's unit signs; the estimator's (user u2sa)
and the HSM's (uid 0 without capabilities) are refused. With the key's mode drifted to
world-readable they are still refused (``InaccessiblePaths=`` in their units), and the RC
mux still signs. A process of the user u2sa outside any unit (an operator in the group u2sa)
cannot read it either.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from staged_code import u2sa_command  # noqa: E402
from systemd_ns import SystemdNamespace, cannot_boot_reason, stage_root, wait_until  # noqa: E402

from u2sa_hw.bus.udp_ports import private_udp_port  # noqa: E402

REASON = cannot_boot_reason()
pytestmark = pytest.mark.skipif(REASON is not None, reason=f"systemd cannot boot here: {REASON}")

UNITS = {"u2sa@est.service": "denied", "u2sa@mux.service": "signed", "u2sa-hsm.service": "denied"}
PROBE = """\
import sys
from pathlib import Path

from u2sa_hw.bus.key import BusKeyError
from u2sa_hw.bus.pilot import read_signer, read_verifier

try:
    signer = read_signer(Path("/etc/u2sa/pilot.key"))
except BusKeyError as exc:
    print("PROBE", sys.argv[1], "denied:", exc, flush=True)
else:
    good = read_verifier(Path("/etc/u2sa/pilot.pub")).check(signer.sign(b"RC_MODE"), b"RC_MODE")
    print("PROBE", sys.argv[1], "signed" if good else "bad-signature", flush=True)
"""
# The unit's own sandbox, user and groups (template or HSM unit, plus install's drop-ins); the probe
# instead of the service.
PROBE_DROPIN = """\
[Service]
Type=oneshot
RemainAfterExit=yes
Restart=no
WatchdogSec=0
ExecStart=
ExecStart=/opt/u2sa/venv/bin/python /opt/pilot-probe.py %n
"""


def write_profile(path: Path, port: int) -> Path:
    path.write_text("\n".join([
        "[vehicle]", 'name = "pilot-key-test"', "system_id = 9", f'lcm_url = "udpm://239.255.76.67:{port}?ttl=0"', "",
        "[services.est]", 'kind = "state_estimator"', "",
        "[services.mux]", 'kind = "rc_mux"',
        'settings = { channels = "throttle=5,steering=6,mode=13", enable_line = 21 }', "",
        "[devices.mux]", 'address = "gpio://gpiochip0/5,6,13,21"', "",
        "[services.hsm]", 'kind = "hsm"', ""]))
    return path


def probes(ns: SystemdNamespace, unit: str) -> list[str]:
    """What the probe said in *unit*, one entry per run."""
    return [line.split(" ", 2)[2] for line in ns.journal("-u", unit).splitlines() if line.startswith(f"PROBE {unit} ")]


def wait_probes(ns: SystemdNamespace, count: int) -> dict[str, str]:
    """The last probe result of each unit, once each has run *count* times."""
    for unit in UNITS:
        assert wait_until(lambda u=unit: len(probes(ns, u)) >= count, timeout=60), (unit, ns.journal_hint(unit))
    return {unit: probes(ns, unit)[-1] for unit in UNITS}


def test_only_the_rc_muxs_unit_reads_the_pilot_key(tmp_path: Path) -> None:
    root = stage_root(tmp_path / "root")
    profile = write_profile(tmp_path / "vehicle.toml", private_udp_port())
    done = subprocess.run([*u2sa_command(root), "install", "--vehicle", str(profile), "--root", str(root),
                           "--venv", "shared"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    key = root / "etc/u2sa/pilot.key"
    group = {line.split(":")[0]: line.split(":") for line in (root / "etc/group").read_text().splitlines()}
    assert (key.stat().st_gid, key.stat().st_mode & 0o7777) == (int(group["u2sa-pilot"][2]), 0o040)
    (root / "opt/pilot-probe.py").write_text(PROBE)
    (root / "opt/pilot-probe.py").chmod(0o644)
    units = root / "etc/systemd/system"
    for unit in UNITS:
        (units / f"{unit}.d").mkdir(exist_ok=True)
        (units / f"{unit}.d/99-probe.conf").write_text(PROBE_DROPIN)
    with SystemdNamespace(root, unit="u2sa.target") as ns:
        first = wait_probes(ns, 1)
        assert first["u2sa@mux.service"] == "signed", ns.journal("-u", "u2sa@mux.service")
        for unit in ("u2sa@est.service", "u2sa-hsm.service"):
            assert first[unit].startswith("denied: cannot read the pilot's private key /etc/u2sa/pilot.key "
                                          "(permission denied)"), (unit, first[unit])
        props = {unit: ns.show(unit, "SupplementaryGroups", "InaccessiblePaths", "DropInPaths") for unit in UNITS}
        assert "u2sa-pilot" in props["u2sa@mux.service"]["SupplementaryGroups"].split(), props
        assert {"dialout", "i2c", "gpio"} <= set(props["u2sa@mux.service"]["SupplementaryGroups"].split()), props
        assert "u2sa-pilot" not in props["u2sa@est.service"]["SupplementaryGroups"].split(), props
        assert "u2sa-pilot" not in props["u2sa-hsm.service"]["SupplementaryGroups"].split(), props
        assert "/etc/u2sa/pilot.key" not in props["u2sa@mux.service"]["InaccessiblePaths"], props
        for unit in ("u2sa@est.service", "u2sa-hsm.service"):
            assert "/etc/u2sa/pilot.key" in props[unit]["InaccessiblePaths"], props
            assert "32-pilot-key.conf" not in props[unit]["DropInPaths"], props
        # A drifted mode (world-readable): the other units still cannot reach it, the RC mux still signs.
        key.chmod(0o444)
        ns.systemctl("restart", *UNITS)
        drifted = wait_probes(ns, 2)
        assert drifted["u2sa@mux.service"] == "signed", drifted
        for unit in ("u2sa@est.service", "u2sa-hsm.service"):
            assert drifted[unit].startswith("denied: cannot read the pilot's private key"), (unit, drifted[unit])
        key.chmod(0o040)
        # Outside any unit: the user u2sa with all its groups (an operator in the group u2sa) cannot read it.
        setpriv = shutil.which("setpriv")
        if setpriv is not None:
            passwd = {line.split(":")[0]: line.split(":") for line in (root / "etc/passwd").read_text().splitlines()}
            mine = [e[2] for g, e in group.items() if "u2sa" in e[3].split(",") or g == "u2sa"]
            as_u2sa = ["setpriv", f"--reuid={passwd['u2sa'][2]}", f"--regid={passwd['u2sa'][3]}",
                       f"--groups={','.join(mine)}", "cat", "/etc/u2sa/pilot.key"]
            refused = ns.run(*as_u2sa, check=False)
            assert refused.returncode != 0 and "Permission denied" in refused.stderr, refused
            assert os.path.exists(key)
