"""Streaming commands end quietly when their reader goes away (issue 26): the SIGPIPE convention.

``u2sa echo STATE_ESTIMATE | head -3`` once never exited and logged a BrokenPipeError
traceback per message (the output is printed from the transport's callback thread). Each
command here runs as a real process whose stdout is a pipe this test closes after a few
lines (or at once); it must exit by itself with status 141 (128 + SIGPIPE, what a shell
shows for ``yes | head -1``) and write nothing about the pipe on stderr.
"""

from __future__ import annotations

import math
import os
import subprocess
import time
from pathlib import Path
from typing import Iterator

import pytest
from conftest import U2SA

from u2sa_hw import lcmtypes as t
from u2sa_hw.cli import SIGPIPE_STATUS
from u2sa_hw.recording.mcap_log import McapLogWriter, RunInfo

EXIT_WITHIN_S = 30.0   # generous: the command exits on its next write after the close, a few ms later


@pytest.fixture
def publisher(lcm_url: str, tmp_path: Path) -> Iterator[subprocess.Popen]:
    """``u2sa pub`` of a StateInformation on STATE_ESTIMATE at 50 Hz until the test ends."""
    proc = subprocess.Popen([*U2SA, "pub", "STATE_ESTIMATE", "StateInformation", "sensor_name=pipe", "x=1.5",
                             "--rate", "50"], cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    yield proc
    proc.terminate()
    proc.wait(timeout=10)


def run_and_close(args: list[str], cwd: Path, *, lines: int) -> tuple[int, str, list[bytes]]:
    """Run ``u2sa ARGS``, read *lines* lines of its stdout, close the pipe; its status, stderr and the lines read."""
    proc = subprocess.Popen([*U2SA, *args], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            stdin=subprocess.DEVNULL, env=dict(os.environ, PYTHONUNBUFFERED="0"))
    assert proc.stdout is not None and proc.stderr is not None
    got = [proc.stdout.readline() for _ in range(lines)]
    proc.stdout.close()   # what `head -3` does after its third line
    try:
        _out, err = proc.communicate(timeout=EXIT_WITHIN_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        _out, err = proc.communicate()
        pytest.fail(f"u2sa {' '.join(args)} still ran {EXIT_WITHIN_S:g} s after its reader closed the pipe; "
                    f"stderr: {err.decode(errors='replace')[-2000:]}")
    return proc.returncode, err.decode(errors="replace"), got


def assert_quiet_sigpipe_exit(status: int, stderr: str) -> None:
    assert "Traceback" not in stderr and "BrokenPipe" not in stderr and "Exception ignored" not in stderr, stderr
    assert status == SIGPIPE_STATUS, (status, stderr)


@pytest.mark.parametrize("json_out", [False, True], ids=["text", "json"])
def test_echo_piped_into_a_reader_that_stops_after_three_lines_exits(publisher: subprocess.Popen, tmp_path: Path,
                                                                     json_out: bool) -> None:
    args = ["echo", "STATE_ESTIMATE", "--wait", *(["--json"] if json_out else [])]
    status, stderr, got = run_and_close(args, tmp_path, lines=3)
    assert all(got), got   # three lines were printed before the reader left
    assert_quiet_sigpipe_exit(status, stderr)


def test_log_echo_piped_into_a_reader_that_stops_exits(tmp_path: Path) -> None:
    log = tmp_path / "run.mcap"
    writer = McapLogWriter(tmp_path, path=log, run=RunInfo(vehicle="rover"))
    t0 = time.time_ns()
    for i in range(2000):   # far more than a pipe holds: the command is still writing when the reader leaves
        s = t.StateInformation().set(x=i * 0.5, y=math.sin(i / 5))
        writer.write("STATE_ESTIMATE", s.encode(), t0 + i * 1_000_000)
    writer.close()
    status, stderr, got = run_and_close(["log", "echo", str(log), "STATE_ESTIMATE"], tmp_path, lines=3)
    assert got[0].startswith(b"--- STATE_ESTIMATE"), got
    assert_quiet_sigpipe_exit(status, stderr)


def test_health_watch_piped_into_a_reader_that_stops_exits(lcm_url: str, tmp_path: Path) -> None:
    status, stderr, got = run_and_close(["health", "--watch", "--interval", "0.05"], tmp_path, lines=3)
    assert b"(no service heard yet)" in got[2], got
    assert_quiet_sigpipe_exit(status, stderr)


def test_topics_whose_reader_left_before_it_printed_exits_quietly(publisher: subprocess.Popen, tmp_path: Path) -> None:
    status, stderr, _got = run_and_close(["topics", "--duration", "0.3"], tmp_path, lines=0)
    assert_quiet_sigpipe_exit(status, stderr)
