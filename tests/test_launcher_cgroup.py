"""The launcher's cgroup hook: every run of every child joins the budget's cgroup before exec.

Real cgroups (v1 ``cpu`` and v2) as root when the machine has them; every cgroup made here
is removed, its processes moved back to the parent group first, even when a test fails.
"""

from __future__ import annotations

import os
import sys
import threading
import uuid
from pathlib import Path
from typing import Iterator

import pytest

from u2sa_hw.launcher import RestartPolicy, SupervisedProcess
from u2sa_hw.launcher.child_setup import CgroupError, check_cgroup, procs_file
from u2sa_hw.realtime import Schedule

V1_CPU = Path("/sys/fs/cgroup/cpu")
V2 = next((p for p in (Path("/sys/fs/cgroup/unified"), Path("/sys/fs/cgroup"))
           if (p / "cgroup.controllers").exists()), None)
SHOW = "import os; print(open('/proc/self/cgroup').read()); print('policy', os.sched_getscheduler(0))"


def _make_cgroup(root: Path | None, what: str) -> Iterator[Path]:
    if root is None or not (root / "cgroup.procs").exists():
        pytest.skip(f"no {what} hierarchy mounted here")
    if os.geteuid() != 0:
        pytest.skip(f"making a {what} group needs root")
    group = root / f"u2sa-test-{uuid.uuid4().hex[:8]}"
    try:
        group.mkdir()
    except OSError as exc:
        pytest.skip(f"cannot make a {what} group: {exc}")
    try:
        yield group
    finally:
        for pid in (group / "cgroup.procs").read_text().split():   # a child left behind: back to the parent
            try:
                (root / "cgroup.procs").write_text(pid)
            except OSError:
                pass
        group.rmdir()


@pytest.fixture
def v1_cpu_group() -> Iterator[Path]:
    """A fresh cgroup v1 ``cpu`` group (its ``cpu.rt_runtime_us`` is 0, the kernel's default for a new group)."""
    yield from _make_cgroup(V1_CPU if (V1_CPU / "tasks").exists() else None, "cgroup v1 cpu")


@pytest.fixture
def v2_group() -> Iterator[Path]:
    """A fresh cgroup v2 group."""
    yield from _make_cgroup(V2, "cgroup v2")


def _run(proc: SupervisedProcess) -> str:
    child = proc.spawn()
    assert child.stdout is not None
    os.set_blocking(child.stdout.fileno(), True)
    out = child.stdout.read().decode()
    child.wait()
    proc.poll()
    return out


def _member(out: str, group: Path, root: Path) -> bool:
    rel = "/" + str(group.relative_to(root))
    return any(line.split(":", 2)[2] == rel for line in out.splitlines() if line.count(":") >= 2)


@pytest.mark.parametrize("fixture, root", [("v1_cpu_group", V1_CPU), ("v2_group", V2)])
def test_every_run_of_a_child_joins_the_cgroup(fixture: str, root: Path, request: pytest.FixtureRequest) -> None:
    group = request.getfixturevalue(fixture)
    proc = SupervisedProcess("probe", [sys.executable, "-c", SHOW], policy=RestartPolicy(), cgroup=group)
    first = _run(proc)
    assert _member(first, group, root), first
    proc.restart("again", grace_s=1.0)
    second = _run(proc)   # a restart lands in the budget too
    assert proc.run_id == 2 and _member(second, group, root), second
    assert not _member(Path("/proc/self/cgroup").read_text(), group, root)   # the launcher itself stays out


def test_a_child_forked_real_time_drops_to_normal_before_joining_a_v1_cpu_group(v1_cpu_group: Path) -> None:
    # u2sa sim runs its own threads SCHED_FIFO, so its children are forked real-time; a FIFO task
    # cannot enter a v1 cpu group with cpu.rt_runtime_us 0 (EINVAL). The child drops first, joins,
    # then asks for its own priority, which the group refuses (EPERM): it runs at normal priority, said why.
    results: dict[str, object] = {}

    def spawn_from_a_real_time_thread() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        except OSError as exc:
            results["skip"] = str(exc)
            return
        proc = SupervisedProcess("probe", [sys.executable, "-c", SHOW], policy=RestartPolicy(),
                                 cgroup=v1_cpu_group, schedule=Schedule(25))
        results["out"] = _run(proc)
        results["warning"] = proc.setup_warning

    thread = threading.Thread(target=spawn_from_a_real_time_thread)
    thread.start()
    thread.join()
    if "skip" in results:
        pytest.skip(f"cannot run a thread SCHED_FIFO here: {results['skip']}")
    out = str(results["out"])
    assert _member(out, v1_cpu_group, V1_CPU), out
    assert f"policy {os.SCHED_OTHER}" in out
    warning = str(results["warning"])
    if (v1_cpu_group / "cpu.rt_runtime_us").exists():   # a kernel with RT group scheduling
        assert "SCHED_FIFO 25 refused" in warning and f"{v1_cpu_group}/cpu.rt_runtime_us" in warning, warning
        assert "runs at normal priority" in warning


def test_a_cgroup_that_is_not_one_is_refused_naming_it(tmp_path: Path) -> None:
    with pytest.raises(CgroupError, match=f"{tmp_path}: not a cgroup directory"):
        check_cgroup(tmp_path)
    (tmp_path / "cgroup.procs").write_text("")
    assert procs_file(tmp_path) == tmp_path / "cgroup.procs"


def test_a_child_that_cannot_join_does_not_start_and_the_error_names_the_cgroup(tmp_path: Path) -> None:
    (tmp_path / "cgroup.procs").mkdir()   # passes the launcher's check as root; the child's write fails
    proc = SupervisedProcess("probe", [sys.executable, "-c", "open('ran', 'w')"], policy=RestartPolicy(),
                             cgroup=tmp_path, cwd=str(tmp_path))
    with pytest.raises(OSError, match=f"cannot join cgroup {tmp_path}: Is a directory"):
        proc.spawn()
    assert proc.proc is None and not (tmp_path / "ran").exists()
