"""bench/sbc.py's pure parts (bench/cpu_budget.py, bench/sbc_figures.py).

Budget lists, the cgroup files for a budget, the headline from a table of step results, and
group set-up and removal.

The cgroup set-up runs against a fake cgroup root made of real files in tmp_path (a plain
directory is not empty, so its rmdir is shutil.rmtree). One test uses the real cpu
controller when this is root and one is mounted; it removes its group. No timing asserts.
"""

from __future__ import annotations

import json
import os
from datetime import datetime
from pathlib import Path

import pytest

from bench.cpu_budget import (BudgetError, CpuBudget, Hierarchy, detect, parse_budgets, read_usage_ns, remove_stale,
                              remove_tree, v1_values, v2_values)
from bench.sbc_figures import RunResult, Step, headline, lost_checks, result_of, table


# -- budget lists and file values -------------------------------------------------------------
def test_parse_budgets_keeps_order_and_accepts_percent_signs() -> None:
    assert parse_budgets("100, 60,40%,30,,20", cpus=2) == [100.0, 60.0, 40.0, 30.0, 20.0]
    assert parse_budgets("150", cpus=2) == [150.0]


@pytest.mark.parametrize("text", ["", "abc", "0", "-5", "201"])
def test_parse_budgets_refuses_what_is_not_a_share_of_the_cores(text: str) -> None:
    with pytest.raises(ValueError):
        parse_budgets(text, cpus=2)


def test_v1_values_set_cfs_quota_and_the_same_share_of_rt_runtime() -> None:
    assert v1_values(30, rt_available_us=950_000) == {"cpu.cfs_period_us": "100000", "cpu.cfs_quota_us": "30000",
                                                      "cpu.rt_runtime_us": "300000"}


def test_v1_rt_runtime_is_capped_at_what_the_parent_can_give_and_absent_without_rt_groups() -> None:
    assert v1_values(100, rt_available_us=950_000)["cpu.rt_runtime_us"] == "950000"
    assert "cpu.rt_runtime_us" not in v1_values(100)


def test_quota_never_goes_below_the_kernels_minimum() -> None:
    assert v1_values(0.1)["cpu.cfs_quota_us"] == "1000"
    assert v2_values(0.1) == {"cpu.max": "1000 100000"}


def test_v2_value_is_quota_and_period() -> None:
    assert v2_values(20) == {"cpu.max": "20000 100000"}
    assert v2_values(150, period_us=200_000) == {"cpu.max": "300000 200000"}


# -- detection ------------------------------------------------------------------------------
def test_detect_v1_with_cpuacct_mounted_apart(tmp_path: Path) -> None:
    (tmp_path / "cpu").mkdir()
    (tmp_path / "cpu" / "cpu.rt_runtime_us").write_text("950000\n")
    mounts = (f"cgroup {tmp_path}/cpu cgroup rw,relatime,cpu 0 0\n"
              f"cgroup {tmp_path}/cpuacct cgroup rw,relatime,cpuacct 0 0\n"
              f"cgroup2 {tmp_path}/unified cgroup2 rw 0 0\n")
    assert detect(mounts=mounts) == Hierarchy(1, tmp_path / "cpu", tmp_path / "cpuacct", realtime=True)


def test_detect_v1_comounted_reads_usage_from_the_cpu_groups(tmp_path: Path) -> None:
    mounts = f"cgroup {tmp_path}/cpu,cpuacct cgroup rw,cpu,cpuacct 0 0\n"
    assert detect(mounts=mounts) == Hierarchy(1, tmp_path / "cpu,cpuacct", None, realtime=False)


def test_detect_v2_needs_the_cpu_controller_enabled_for_groups(tmp_path: Path) -> None:
    (tmp_path / "cgroup.controllers").write_text("cpuset cpu io memory pids\n")
    (tmp_path / "cgroup.subtree_control").write_text("memory pids\n")
    mounts = f"cgroup2 {tmp_path} cgroup2 rw,nsdelegate 0 0\n"
    with pytest.raises(BudgetError, match=r"\+cpu"):
        detect(mounts=mounts)
    (tmp_path / "cgroup.subtree_control").write_text("cpu memory pids\n")
    assert detect(mounts=mounts) == Hierarchy(2, tmp_path)


def test_detect_without_a_cpu_controller_says_so(tmp_path: Path) -> None:
    (tmp_path / "cgroup.controllers").write_text("hugetlb\n")
    with pytest.raises(BudgetError, match="no cpu controller"):
        detect(mounts=f"cgroup2 {tmp_path} cgroup2 rw 0 0\n")


# -- groups on a fake root ---------------------------------------------------------------------
def fake_v1(tmp_path: Path) -> Hierarchy:
    cpu, acct = tmp_path / "cpu", tmp_path / "cpuacct"
    for root in (cpu, acct):
        root.mkdir()
        (root / "cgroup.procs").write_text("")
    (cpu / "cpu.rt_runtime_us").write_text("950000\n")
    other = cpu / "someone-else"      # another group holding RT runtime: ours gets what is left
    other.mkdir()
    (other / "cpu.rt_runtime_us").write_text("750000\n")
    return Hierarchy(1, cpu, acct, realtime=True)


def test_v1_budget_writes_its_files_and_removes_its_groups(tmp_path: Path) -> None:
    h = fake_v1(tmp_path)
    budget = CpuBudget(h, 30, name="u2sa-sbc-1", rmdir=remove_tree).create()
    group = h.cpu_root / "u2sa-sbc-1"
    assert (group / "cpu.cfs_quota_us").read_text() == "30000"
    assert (group / "cpu.cfs_period_us").read_text() == "100000"
    assert (group / "cpu.rt_runtime_us").read_text() == "200000"   # 950000 - 750000 held elsewhere
    assert budget.usage_file() == (h.acct_root / "u2sa-sbc-1" / "cpuacct.usage", True)
    (group / "cgroup.procs").write_text("4242\n")   # a task left behind
    budget.remove()
    assert not group.exists() and not (h.acct_root / "u2sa-sbc-1").exists()
    assert (h.cpu_root / "cgroup.procs").read_text() == "4242"
    assert (h.cpu_root / "someone-else").exists()


def test_whole_sim_budget_counts_the_sim_process_in_v2(tmp_path: Path) -> None:
    (tmp_path / "cgroup.procs").write_text("")
    h = Hierarchy(2, tmp_path)
    with CpuBudget(h, 40, whole_sim=True, name="u2sa-sbc-2", rmdir=remove_tree) as budget:
        assert (tmp_path / "u2sa-sbc-2" / "cpu.max").read_text() == "40000 100000"
        assert budget.usage_file() == (tmp_path / "u2sa-sbc-2" / "cpu.stat", True)
    assert not (tmp_path / "u2sa-sbc-2").exists()
    assert CpuBudget(h, 40, name="x").usage_file() == (tmp_path / "x" / "cpu.stat", False)


def test_stale_groups_of_benches_gone_are_removed_and_live_ones_kept(tmp_path: Path) -> None:
    h = fake_v1(tmp_path)
    gone = h.cpu_root / "u2sa-sbc-999999999"   # no such pid
    mine = h.cpu_root / f"u2sa-sbc-{os.getpid()}"
    for path in (gone, mine):
        path.mkdir()
    assert remove_stale(h) == [str(gone)]
    assert mine.exists() and (h.cpu_root / "someone-else").exists()


def test_a_failed_write_removes_what_was_made(tmp_path: Path) -> None:
    h = fake_v1(tmp_path)
    (h.cpu_root / "u2sa-sbc-3").mkdir()   # already there: mkdir fails before anything is written
    with pytest.raises(FileExistsError):
        CpuBudget(h, 30, name="u2sa-sbc-3", rmdir=remove_tree).create()
    assert not (h.acct_root / "u2sa-sbc-3").exists()


def test_usage_is_read_in_ns_from_v1_and_v2_files(tmp_path: Path) -> None:
    (tmp_path / "cpuacct.usage").write_text("123456789\n")
    (tmp_path / "cpu.stat").write_text("usage_usec 2500\nuser_usec 2000\nsystem_usec 500\n")
    assert read_usage_ns(tmp_path / "cpuacct.usage") == 123456789
    assert read_usage_ns(tmp_path / "cpu.stat") == 2_500_000


# -- the headline -----------------------------------------------------------------------------
def step(percent: float, *, completed: bool = True, losses: int = 0, rc: float = 40.0, manual: float = 20.0,
         missed: int = 0) -> Step:
    return Step(percent, [
        RunResult("mission", "completed" if completed else "failed", "" if completed else "timed out",
                  mission_time_s=40.0, losses=losses, stack_pct=12.0),
        RunResult("rc_loss", "completed", times_ms=[rc, rc / 2], never=missed),
        RunResult("manual_switch", "completed", times_ms=[manual])])


def test_headline_is_the_lowest_budget_that_holds_with_every_higher_one() -> None:
    steps = [step(100), step(60), step(40), step(30, manual=75.0), step(20, losses=2)]
    text = headline(steps)
    assert "down to 40 %" in text and "at 30 %: manual_switch: max 75 ms > 50 ms" in text
    assert steps[3].problems() == ["manual_switch: max 75 ms > 50 ms"]
    assert steps[4].problems() == ["2 autonomy losses"]


def test_headline_is_the_lowest_that_held_and_names_a_failure_above_it_as_noise() -> None:
    text = headline([step(20), step(100), step(30, completed=False)])
    assert "down to 20 %" in text and "yet not at 30 % (mission failed: timed out): noise" in text


def test_headline_when_nothing_holds_and_when_everything_does() -> None:
    assert "nothing held, not even at 100 %" in headline([step(100, missed=1), step(50, manual=60.0)])
    assert "down to 20 %" in headline([step(100), step(20)], whole_sim=True)
    assert "whole u2sa sim" in headline([step(20)], whole_sim=True)


def test_losses_right_after_a_simulated_receiver_stall_count_only_when_the_sim_is_in_the_budget() -> None:
    services = step(100, losses=3)
    services.runs[0].sim_losses = 3
    assert services.problems() == []
    assert "3 autonomy losses right after the simulated RC receiver" in services.notes()[0]
    whole = step(100, losses=3)
    whole.runs[0].sim_losses, whole.whole_sim = 3, True
    assert whole.problems() == ["3 autonomy losses"] and whole.notes() == []
    services.runs[0].losses = 4   # one loss the stalls do not explain
    assert services.problems() == ["1 autonomy loss"]


def test_table_has_a_row_per_budget_highest_first() -> None:
    lines = table([step(30, rc=250.0), step(100)])
    assert lines[2].split()[0] == "100" and lines[3].split()[0] == "30"
    assert "188/250" in lines[3] and lines[3].endswith("no") and lines[2].endswith("yes")


def test_autonomy_losses_name_the_checks_the_mux_dropped_autonomy_for(tmp_path: Path) -> None:
    log = tmp_path / "services.log"
    log.write_text("rc | 2026-12-04T20:38:59.963 WARN rc [1] pre-arm check lost while autonomous: estimator: x\n"
                   "rc | 2026-12-04T20:39:00.100 WARN rc [1] pre-arm check lost while autonomous: rc_link: no valid\n"
                   "rc | 2026-12-04T20:39:01.000 WARN rc [1] pre-arm check lost while autonomous: estimator: x\n"
                   "rc | 2026-12-04T20:39:29.322 WARN rc [1] pre-arm check lost while autonomous: imu: stopped\n")
    assert lost_checks(log)["imu"] == 1
    causes = lost_checks(log, until=datetime.fromisoformat("2026-12-04T20:39:10").timestamp())
    assert causes == {"estimator": 2, "rc_link": 1}   # the imu stopped after the drive: not a lost check
    lossy = step(30, losses=3)
    lossy.runs[0].causes = causes
    assert lossy.problems() == ["3 autonomy losses (checks lost: estimator x2, rc_link x1)"]
    lossy.runs[0].rc_stalls = 2
    assert "simulated RC receiver itself stalled 2 times" in lossy.problems()[0]
    assert lost_checks(tmp_path / "missing.log") == {}


def test_result_of_a_scenario_tells_never_neutral_from_nothing_moving(tmp_path: Path) -> None:
    def event(after: float | None, moving: bool) -> dict:
        return {"action": "rc_loss", "event": "rc_loss", "all_neutral_after_ms": after,
                "outputs": {"left_wheel": {"at_event": {"value": 50.0 * moving, "neutral": not moving}}}}

    summary = {"result": "completed", "reason": "", "autonomy_interruptions": [], "services": {"rc": {"restarts": 1}},
               "scenario": {"events": [event(30.0, True), event(None, True), event(0.0, False),
                                       {"action": "rc_return", "event": "rc_return", "all_neutral_after_ms": None,
                                        "outputs": {}}]}}
    (tmp_path / "summary.json").write_text(json.dumps(summary))
    run = result_of("rc_loss", tmp_path, (0, 0), exit_code=0)
    assert (run.times_ms, run.never, run.idle, run.restarts) == ([30.0], 1, 1, 1)
    assert Step(100, [run]).problems() == ["rc_loss: 1 event(s) whose outputs never went neutral"]


def test_result_of_a_run_that_wrote_no_summary(tmp_path: Path) -> None:
    run = result_of("mission", tmp_path, (10, 2), exit_code=1)
    assert run.result == "failed" and "no summary" in run.reason and run.periods == (10, 2)


# -- the real controller ----------------------------------------------------------------------
def test_a_real_budget_group_is_made_and_removed() -> None:
    if os.geteuid() != 0:
        pytest.skip("needs root to create a cgroup")
    try:
        h = detect()
    except BudgetError as exc:
        pytest.skip(str(exc))
    budget = CpuBudget(h, 25, name=f"u2sa-sbc-test-{os.getpid()}")
    try:
        budget.create()
        quota = "cpu.max" if h.version == 2 else "cpu.cfs_quota_us"
        assert (budget.group / quota).read_text().split()[0] == "25000"
    finally:
        assert budget.remove() == []
    assert not budget.group.exists()
