"""Recording a simulation, end to end: ``u2sa sim --record`` writes a complete log of the run, and a
separate ``u2sa record`` started before the simulation is killed (SIGKILL) mid-run; its file is
recovered with ``u2sa log recover`` and replayed into every driver with ``--fast --compare``,
which finds no differences: every stream, the RC mux's RC_MODE and MANUAL_CMD included."""

from __future__ import annotations

import os
import re
import signal
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import pytest
from conftest import REPO, U2SA, wait_until
from recorded_sim import held_up

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.recording.log_reader import LogFile
from u2sa_hw.bus.udp_ports import private_lcm_url, private_udp_port

GROUND = REPO / "examples" / "ground_vehicle" / "vehicle.toml"
DRIVERS = {"gps", "compass", "imu", "wheels", "pan", "rc"}
AUTONOMOUS_MESSAGES = 20   # RC_MODE at 10 Hz: about two seconds of autonomous driving before the kill


@dataclass
class SimRecordings:
    """What the module's one simulation run left behind."""

    workdir: Path
    sim_out: Path
    killed: Path          # the SIGKILLed `u2sa record` file
    sim_returncode: int


def _autonomous_messages(path: Path) -> int:
    if not path.exists():
        return 0
    n = 0
    for m in LogFile(path).messages(ch.RC_MODE):   # a file being written reads up to its last whole chunk
        n += t.RcMode.decode(m.data).autonomy_enabled
    return n


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SimRecordings]:
    workdir = tmp_path_factory.mktemp("sim-record")
    url = private_lcm_url()
    env = dict(os.environ, PYTHONPATH=str(REPO), U2SA_LCM_URL=url, PYTHONUNBUFFERED="1")
    killed = workdir / "external.mcap"
    recorder = subprocess.Popen([*U2SA, "record", "-o", str(killed), "--vehicle", str(GROUND)], cwd=workdir, env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    sim: subprocess.Popen | None = None
    bus = BusClient(url)
    try:
        def recorder_listening() -> bool:   # the recorder opens its file with the first message it gets
            bus.publish("TEST_PROBE", t.Health())
            return killed.exists()

        wait_until(recorder_listening, timeout=30, interval=0.2, message="u2sa record to listen")
        sim_out = workdir / "sim-out"
        # The session's key, which the external recorder has too (u2sa sim would make a fresh one).
        sim = subprocess.Popen([*U2SA, "sim", "--out", str(sim_out), "--lcm-url", url, "--can-port",
                                str(private_udp_port()), "--record", "--timeout", "90",
                                "--bus-key", os.environ["U2SA_BUS_KEY_FILE"]], cwd=REPO, env=env,
                               stdout=(workdir / "sim.stdout").open("w"), stderr=subprocess.DEVNULL)
        wait_until(lambda: _autonomous_messages(killed) >= AUTONOMOUS_MESSAGES or sim.poll() is not None,
                   timeout=120, interval=1.0, message="the simulated rover driving autonomously")
        assert sim.poll() is None, "the simulation ended before the recorder could be killed mid-run"
        recorder.send_signal(signal.SIGKILL)
        recorder.wait(timeout=10)
        sim.send_signal(signal.SIGINT)   # the simulation stops its services (its own recorder finishes its file)
        sim.wait(timeout=60)
        yield SimRecordings(workdir, sim_out, killed, sim.returncode)
    finally:
        bus.close()
        for proc in (recorder, sim):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()


def cli(*args: str, cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.pop("U2SA_LCM_URL", None)
    return subprocess.run([*U2SA, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.mark.timeout(300)
def test_sim_record_writes_a_complete_log_of_the_run(recordings: SimRecordings) -> None:
    files = sorted((recordings.sim_out / "recording").glob("*.mcap"))
    assert len(files) == 1, files
    printed = (recordings.workdir / "sim.stdout").read_text()
    assert f"recording: {files[0]} (" in printed, printed     # u2sa sim --record names the file it wrote
    log = LogFile(files[0])
    summary = log.scan()
    assert log.contents.complete and not log.contents.problem
    assert {"vehicle.toml", "config/rc.toml", "config/wheels.toml"} <= set(log.contents.attachments)
    channels = {c.channel for c in summary.channels}
    assert {ch.STATE_ESTIMATE, ch.ACTUATOR_CMD, ch.RC_MODE, ch.HEALTH} <= channels
    # the drivers tap their ports while --record is on, so the recording can be replayed
    assert {"gps", "compass", "imu", "wheels", "rc"} <= set(summary.devices)


# A recording ends before the services do (the recorder is killed, or stops first when the simulation is
# interrupted): the last messages a service published on its way out may not reach it. At 20 Hz an RC_MODE
# a loaded machine took 100 ms to deliver is two more than the recording holds, so three at each end of a
# stream are not counted against the replay (u2sa replay --edge; the default is one).
EDGE = 3
# Every recorded RC_MODE and MANUAL_CMD kept its pilot signature, and the replay checked it with the recorded key.
PILOT_CHECKED = re.compile(r"pilot messages: [1-9]\d* checked with the recorded pilot key [0-9a-f]{8}, all signed")

def assert_every_stream_the_same(res: subprocess.CompletedProcess, log: Path) -> None:
    """The replay ran and compared, and every stream is the same: the RC mux's RC_MODE and MANUAL_CMD too
    (their timed messages fall on the recorded clock's grid with the state as of their due time, and the
    pre-arm inputs are the recorded ones: docs/replay.md, Determinism). Only the rows of a service the
    recording machine held up (held_up: a loaded CI machine) are reported instead of gated."""
    assert res.returncode in (0, 1), res.stdout + res.stderr
    rows = [line for line in res.stdout.splitlines() if line.rstrip().endswith(("same", "DIFFERENT", "new"))
            and " [" in line]
    assert rows and any(row.startswith("RC_MODE [rc]") for row in rows) and any(
        row.startswith("MANUAL_CMD [rc]") for row in rows), res.stdout
    held = held_up(log)
    reported = [row for row in rows if row.split(" [", 1)[1].split("]", 1)[0] in held]
    gated = [row for row in rows if row not in reported]
    assert all(row.rstrip().endswith("same") for row in gated), res.stdout
    if held:
        print(f"held up while recording ({held}): their streams reported, not gated:\n" + "\n".join(reported))
    else:
        assert res.returncode == 0, res.stdout + res.stderr


@pytest.mark.timeout(300)
def test_killed_recorder_log_recovers_and_replays_with_no_differences(recordings: SimRecordings) -> None:
    work = recordings.workdir
    info = cli("log", "info", str(recordings.killed), cwd=work)
    assert info.returncode == 0 and "NOT COMPLETE" in info.stdout, info.stdout + info.stderr
    fixed = work / "recovered.mcap"
    rec = cli("log", "recover", str(recordings.killed), "-o", str(fixed), cwd=work)
    assert rec.returncode == 0 and "truncated" in rec.stdout, rec.stdout + rec.stderr
    log = LogFile(fixed)
    summary = log.scan()
    assert log.contents.complete and DRIVERS <= set(summary.devices), summary.devices
    res = cli("replay", str(fixed), "--fast", "--compare", "--edge", str(EDGE), "-o", str(work / "replayed.mcap"),
              cwd=work, timeout=240)
    assert_every_stream_the_same(res, fixed)
    assert PILOT_CHECKED.search(res.stdout), res.stdout   # u2sa log recover keeps the trailers and the key
    compared = {line.split(" [", 1)[1].split("]", 1)[0] for line in res.stdout.splitlines() if " [" in line
                and line.rstrip().endswith("same")}
    assert DRIVERS <= compared, res.stdout


@pytest.mark.timeout(300)
def test_the_simulations_own_recording_replays_with_no_differences(recordings: SimRecordings) -> None:
    """The launcher starts the recorder first and the drivers once it is ready, so its log holds their start-up."""
    files = sorted((recordings.sim_out / "recording").glob("*.mcap"))
    work = recordings.workdir
    res = cli("replay", str(files[0]), "--fast", "--compare", "--edge", str(EDGE),
              "-o", str(work / "sim-replayed.mcap"), cwd=work, timeout=240)
    assert_every_stream_the_same(res, files[0])
    assert PILOT_CHECKED.search(res.stdout), res.stdout
    compared = {line.split(" [", 1)[1].split("]", 1)[0] for line in res.stdout.splitlines() if " [" in line
                and line.rstrip().endswith("same")}
    assert DRIVERS <= compared, res.stdout
    # What the replayed drivers hear from the rest of the system is the recorded commands (ACTUATOR_CMD), not
    # its Health and estimates: the RC mux takes those from its replay chip in order with its edges and
    # ignores them on the bus, so republishing them would only load the replay bus.
    heard: dict[str, set[str]] = {}
    for m in LogFile(work / "sim-replayed.mcap").messages(r"ACTUATOR_CMD|STATE_ESTIMATE|U2SA_HEALTH"):
        source = t.Health.decode(m.data).name if m.channel == ch.HEALTH else "-"
        heard.setdefault(m.channel, set()).add(source)
    assert "ACTUATOR_CMD" in heard and "STATE_ESTIMATE" not in heard, heard
    assert heard[ch.HEALTH] <= DRIVERS, heard   # the replayed drivers' own health only
