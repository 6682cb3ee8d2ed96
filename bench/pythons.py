"""What the lean stack relies on, checked under this interpreter, and a service's import footprint.

`make test-pythons` runs it in each interpreter's venv (see docs/python-versions.md):

- ``gc.freeze()`` after start-up (u2sa_hw/service/contract.py ``settle_memory``);
- kernel thread names written to ``/proc/self/task/TID/comm`` (u2sa_hw/service/health.py);
- ``os.memfd_create`` for the C library's captured stderr (u2sa_hw/bus/lcm_open.py);
- ``os.times()`` for a service's CPU % (u2sa_hw/service/health.py ``ProcessStats``);
- python-can imported only when a CAN port opens (u2sa_hw/ports/can/port.py).

Then, in a fresh interpreter, the memory of a service-like import set (PSS, private and RSS from
``/proc/self/smaps_rollup``, peak RSS from ``VmHWM``) beside a bare interpreter's. PSS depends on
what else runs: libpython's pages are split among every process of the same interpreter, so
compare versions by the private figure. Exit 1 when a
check fails; the figures are printed, not judged.
"""

from __future__ import annotations

import gc
import os
import subprocess
import sys
import threading
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))   # the repository's drivers package, not bench/drivers.py

SERVICE_IMPORTS = "import u2sa_hw.cli.service_cmd, u2sa_hw.service.contract, u2sa_hw.services.mission.service"

MEMORY = """
import sys
{imports}
fields = {{}}
with open("/proc/self/smaps_rollup", encoding="ascii") as f:
    for line in f:
        key, _, rest = line.partition(":")
        if key in ("Rss", "Pss", "Private_Clean", "Private_Dirty"):
            fields[key] = int(rest.split()[0])
with open("/proc/self/status", encoding="ascii") as f:
    for line in f:
        if line.startswith("VmHWM:"):
            fields["VmHWM"] = int(line.split()[1])
print(fields["Pss"], fields["Private_Clean"] + fields["Private_Dirty"], fields["Rss"], fields["VmHWM"], len(sys.modules))
"""


def check_gc_freeze() -> str:
    gc.collect()
    gc.freeze()
    frozen = gc.get_freeze_count()
    gc.unfreeze()
    assert frozen > 0, "gc.freeze() froze nothing"
    return f"{frozen} objects frozen"


def check_thread_comm() -> str:
    from u2sa_hw.bus.threads import name_native_thread

    release = threading.Event()
    thread = threading.Thread(target=release.wait, daemon=True)
    thread.start()
    try:
        name_native_thread(thread, "bus pythons-check")
        with open(f"/proc/self/task/{thread.native_id}/comm", encoding="ascii") as f:
            name = f.read().strip()
    finally:
        release.set()
        thread.join()
    assert name == "bus pythons-check"[:15], f"thread comm reads {name!r}"   # the kernel keeps 15 bytes
    return f"comm {name!r}"


def check_memfd() -> str:
    from u2sa_hw.bus.lcm_open import captured_c_stderr

    with captured_c_stderr() as printed:
        os.write(2, b"from C\n")
    assert printed == ["from C\n"], f"captured {printed!r}"
    return "fd 2 captured"


def check_os_times() -> str:
    from u2sa_hw.service.health import ProcessStats

    stats = ProcessStats()
    sum(i * i for i in range(200_000))
    cpu, rss = stats.sample()
    assert cpu >= 0 and rss > 0, (cpu, rss)
    return f"cpu {cpu} %, rss {rss >> 20} MB"


def check_lazy_can() -> str:
    import u2sa_hw.drivers.can_motor.odrive.driver  # noqa: F401  (the RC mux imports the CAN drivers for their names)
    import u2sa_hw.drivers.can_motor.vesc.driver  # noqa: F401
    import u2sa_hw.ports.can.port as can_port

    assert "can" not in sys.modules, "python-can loaded before any CAN port opened"
    port = can_port.open_can(device="pythons-check", interface="virtual", channel="pythons-check")
    port.close()
    assert "can" in sys.modules
    return f"python-can {sys.modules['can'].__version__} loaded by the first open_can"


def memory(imports: str) -> tuple[int, int, int, int, int]:
    """PSS, private (USS), RSS and peak RSS in kB, and the module count, of a fresh interpreter after *imports*."""
    out = subprocess.run([sys.executable, "-c", MEMORY.format(imports=imports)], capture_output=True, text=True,
                         check=True, timeout=60, cwd=REPO).stdout
    pss, uss, rss, hwm, modules = (int(x) for x in out.split())
    return pss, uss, rss, hwm, modules


def main() -> int:
    print(f"python {sys.version.split()[0]} ({sys.executable})")
    failed = 0
    for check in (check_gc_freeze, check_thread_comm, check_memfd, check_os_times, check_lazy_can):
        name = check.__name__.removeprefix("check_")
        try:
            print(f"  {name:12} ok: {check()}")
        except Exception as exc:  # noqa: BLE001  (every check reports, then the exit code tells)
            failed += 1
            print(f"  {name:12} FAILED: {type(exc).__name__}: {exc}")
    bare = memory("")
    service = memory(SERVICE_IMPORTS)
    for label, (pss, uss, rss, hwm, modules) in (("bare interpreter", bare), ("service imports", service)):
        print(f"  {label:16} PSS {pss / 1024:5.1f} MB  private {uss / 1024:5.1f} MB  RSS {rss / 1024:5.1f} MB"
              f"  peak RSS {hwm / 1024:5.1f} MB  {modules} modules")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
