"""A corpus of recordings of varied runs (issue 24), built by the tests once per session: both example
vehicles (and the boat), the sticks scenario, an RC loss, a GPS fix loss, a manual switch, a driver killed and
restarted mid-recording, recordings started while the stack runs (one ended by --duration, one cut by SIGKILL and
recovered with ``u2sa log recover``, one started while it drives under autonomy), and ``u2sa record`` of a ``u2sa mock`` + ``u2sa run`` stack. Each run drives for a few seconds only; the runs go two at a time.

``build_corpus(dir)`` writes ``<dir>/<name>.mcap`` for each and returns ``{name: path}``; the tests
(tests/test_replay_corpus.py) and ``bench/replay_corpus.py`` (``replay-check`` over it under
``bench/cpu_hog.py``) share it.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[1]
U2SA = [sys.executable, "-m", "u2sa_hw.cli"]
GROUND = REPO / "examples" / "ground_vehicle" / "vehicle.toml"
ACKERMANN = REPO / "examples" / "ackermann_rover" / "vehicle.toml"

# Short scenarios (times after autonomy engaged; the shipped ones last 8-16 s each).
SCENARIOS = {
    "sticks": """name = "sticks-short"\nengage = false\nend_s = 3.5
[[event]]\nat_s = 0.5\naction = "sticks"\nthrottle = 0.5
[[event]]\nat_s = 1.5\naction = "sticks"\nsteering = 0.5
[[event]]\nat_s = 2.5\naction = "centre"
""",
    "rc-loss": """name = "rc-loss-short"\nend_s = 4.0
[[event]]\nat_s = 1.0\naction = "rc_loss"
[[event]]\nat_s = 2.0\naction = "rc_return"
[[event]]\nat_s = 2.5\naction = "reengage"
""",
    "gps-fix-loss": """name = "gps-fix-loss-short"\nend_s = 4.5
[[event]]\nat_s = 1.0\naction = "gps_fix"\nfix = false
[[event]]\nat_s = 2.5\naction = "gps_fix"\nfix = true
[[event]]\nat_s = 3.0\naction = "reengage"
""",
    "manual-switch": """name = "manual-switch-short"\nend_s = 3.5
[[event]]\nat_s = 1.0\naction = "mode"\nvalue = "manual"
[[event]]\nat_s = 2.0\naction = "mode"\nvalue = "autonomous"
""",
    # the launcher restarts the killed compass driver: the recording holds both of its runs
    "restart": """name = "restart-short"\nend_s = 5.0
[[event]]\nat_s = 1.0\naction = "signal"\nservice = "compass"\nsignal = "KILL"
""",
}


def _env() -> dict[str, str]:
    env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1", U2SA_SIM_REALTIME="off")
    env.pop("U2SA_LCM_URL", None)   # u2sa sim picks private ports
    return env


def _sim(work: Path, *args: str, timeout: float = 150) -> Path:
    """``u2sa sim --record`` in *work*; its recording."""
    out = work / "sim-out"
    done = subprocess.run([*U2SA, "sim", "--out", str(out), "--record", *args], cwd=REPO, env=_env(),
                          capture_output=True, text=True, timeout=timeout)
    files = sorted((out / "recording").glob("*.mcap"))
    if not files:
        raise RuntimeError(f"u2sa sim {' '.join(args)} wrote no log (status {done.returncode}): "
                           f"{done.stdout[-1500:]}{done.stderr[-1500:]}")
    return files[0]


def _scenario(name: str) -> Callable[[Path], dict[str, Path]]:
    def run(work: Path) -> dict[str, Path]:
        scenario = work / f"{name}.toml"
        scenario.write_text(SCENARIOS[name])
        return {name: _sim(work, "--scenario", str(scenario), "--timeout", "40")}
    return run


def _vehicle(name: str, profile: Path, timeout_s: str = "10") -> Callable[[Path], dict[str, Path]]:
    def run(work: Path) -> dict[str, Path]:
        return {name: _sim(work, "--vehicle", str(profile), "--timeout", timeout_s)}
    return run


def _wait(predicate: Callable[[], bool], timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > end:
            raise RuntimeError(f"timed out waiting for {what}")
        time.sleep(0.2)   # polling a condition, not timing


def _autonomy_engaged(env: dict[str, str], cwd: Path, timeout: float) -> None:
    """Return once the RC mux says autonomy is enabled (``u2sa echo RC_MODE --json``), or raise after *timeout*."""
    import json
    import threading

    echo = subprocess.Popen([*U2SA, "echo", "RC_MODE", "--json", "--wait", "--vehicle", str(GROUND)], cwd=cwd,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    engaged = threading.Event()

    def read() -> None:
        for line in echo.stdout:   # type: ignore[union-attr]
            try:
                if json.loads(line).get("autonomy_enabled") is True:
                    engaged.set()
                    return
            except (ValueError, AttributeError):
                continue

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        if not engaged.wait(timeout):
            raise RuntimeError(f"the simulation did not engage autonomy within {timeout:g} s")
    finally:
        echo.kill()
        echo.wait()


def _mid_run(work: Path) -> dict[str, Path]:
    """The ground vehicle's simulation with three ``u2sa record`` started while it runs: one ends by
    --duration, one is killed with SIGKILL and recovered (both started as the stack comes up), and one started
    once autonomy is engaged (``mid-drive``: the RC mux armed and granted autonomy before its cut); and the
    simulation's own recording."""
    from u2sa_hw.bus.udp_ports import private_lcm_url, private_udp_port

    url = private_lcm_url()
    env = dict(_env(), U2SA_LCM_URL=url)
    out = work / "sim-out"
    sim = subprocess.Popen([*U2SA, "sim", "--out", str(out), "--lcm-url", url, "--can-port", str(private_udp_port()),
                            "--record", "--timeout", "14", "--bus-key", os.environ["U2SA_BUS_KEY_FILE"]],
                           cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    recorders: list[subprocess.Popen] = []
    try:
        # the stack runs once the simulation's own recording holds the drivers' raw input
        def running() -> bool:
            files = sorted((out / "recording").glob("*.mcap"))
            return bool(files) and files[0].stat().st_size > 200_000
        _wait(running, 90, "the simulation to drive")
        timed, killed = work / "mid-run.mcap", work / "killed.mcap"
        for path, extra in ((timed, ["--duration", "4"]), (killed, [])):
            recorders.append(subprocess.Popen([*U2SA, "record", "-o", str(path), "--vehicle", str(GROUND), *extra],
                                              cwd=work, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        _autonomy_engaged(env, work, 90)
        drive = work / "mid-drive.mcap"
        recorders.append(subprocess.Popen([*U2SA, "record", "-o", str(drive), "--vehicle", str(GROUND), "--duration",
                                           "3"], cwd=work, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        recorders[0].wait(timeout=60)
        recorders[2].wait(timeout=60)
        recorders[1].send_signal(signal.SIGKILL)
        recorders[1].wait(timeout=10)
        sim.wait(timeout=90)
    finally:
        for proc in (sim, *recorders):
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    recovered = work / "killed-recovered.mcap"
    done = subprocess.run([*U2SA, "log", "recover", str(killed), "-o", str(recovered)], cwd=work, env=_env(),
                          capture_output=True, text=True, timeout=60)
    if done.returncode != 0 or "truncated" not in done.stdout:
        raise RuntimeError(f"u2sa log recover: {done.stdout}{done.stderr}")
    return {"ground-sim": sorted((out / "recording").glob("*.mcap"))[0], "mid-run": timed,
            "killed-recovered": recovered, "mid-drive": drive}


def _raw_recording_profile(sim_profile: Path, out: Path, url: str) -> bool:
    """Write *out*: u2sa mock's profile (*sim_profile*) with record_raw on for every driver and its bus on
    *url*, what a team does to its own profile to record logs that replay. False while u2sa mock has not
    finished writing its profile."""
    import tomllib

    import tomli_w

    from u2sa_hw.hil.replay_plan import declared_fields

    try:
        data = tomllib.loads(sim_profile.read_text())
    except (OSError, tomllib.TOMLDecodeError):
        return False
    if "vehicle" not in data or "services" not in data:
        return False
    data["vehicle"]["lcm_url"] = url
    recording = [table for table in data["services"].values() if "record_raw" in declared_fields(table["kind"])]
    if not recording:
        raise RuntimeError(f"{sim_profile}: no service declares record_raw (could its driver modules be imported?)")
    for table in recording:
        table.setdefault("settings", {})["record_raw"] = True
    out.write_text(tomli_w.dumps(data))
    return True


def _mock_run(work: Path) -> dict[str, Path]:
    """``u2sa record`` of a ``u2sa mock`` + ``u2sa run`` stack, as a team runs it by hand: the recording starts
    first, so it holds every driver's start-up, and ends with Ctrl-C once it holds a few seconds of running."""
    from u2sa_hw.bus.udp_ports import private_lcm_url, private_udp_port

    url = private_lcm_url()
    env = dict(_env(), U2SA_LCM_URL=url)
    run_dir = work / "sim"
    log = work / "mock-run.mcap"
    mock = subprocess.Popen([*U2SA, "mock", "--vehicle", str(GROUND), "--run-dir", str(run_dir),
                             "--can-port", str(private_udp_port())], cwd=work, env=env, stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    procs = [mock]
    try:
        profile = work / "vehicle.toml"
        _wait(lambda: _raw_recording_profile(run_dir / "vehicle.toml", profile, url), 60,
              "u2sa mock to write its profile")
        record = subprocess.Popen([*U2SA, "record", "-o", str(log), "--vehicle", str(profile)], cwd=work, env=env,
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        procs.append(record)   # (its file appears with the first message it hears)
        procs.append(subprocess.Popen([*U2SA, "run", "--vehicle", str(profile)], cwd=work, env=env,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        _wait(lambda: log.exists() and log.stat().st_size > 300_000, 120, "the stack's traffic in the recording")
        for proc in (record, *procs[2:], mock):   # the recording ends first, then the stack, then its mocks
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=90)
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    return {"mock-run": log}


JOBS: dict[str, Callable[[Path], dict[str, Path]]] = {
    "mid-run": _mid_run,
    "mock-run": _mock_run,
    "ackermann": _vehicle("ackermann-sim", ACKERMANN),
    "boat": _vehicle("boat-sim", REPO / "examples" / "boat" / "vehicle.toml"),
    **{name: _scenario(name) for name in SCENARIOS},
}


def build_corpus(corpus: Path, *, workers: int = 2) -> dict[str, Path]:
    """Build every recording into *corpus* (``<name>.mcap``); returns ``{name: path}``. Two runs at a time on
    2 cores (*workers*): the corpus is about varied runs, not about load (bench/replay_corpus.py)."""
    corpus.mkdir(parents=True, exist_ok=True)
    work = corpus.parent / f"{corpus.name}-work"
    if "U2SA_BUS_KEY_FILE" not in os.environ:   # outside the test session (the bench): a key of the corpus's own
        from u2sa_hw.bus.run_keys import fresh_key_file
        (work / "key").mkdir(parents=True, exist_ok=True)
        os.environ["U2SA_BUS_KEY_FILE"] = str(fresh_key_file(str(work / "key")))

    # the driver modules imported here, once: the jobs' threads importing them at once can meet a module
    # another thread is still initialising (declared_fields then finds no fields)
    from u2sa_hw.hil.replay_plan import declared_fields
    from u2sa_hw.registry import SERVICE_KINDS

    for kind in SERVICE_KINDS:
        declared_fields(kind)

    def job(name: str) -> dict[str, Path]:
        where = work / name
        if where.exists():
            shutil.rmtree(where)   # a build into a used directory starts clean
        where.mkdir(parents=True)
        return JOBS[name](where)

    logs: dict[str, Path] = {}
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for made in pool.map(job, list(JOBS)):
            for name, path in made.items():
                dst = corpus / f"{name}.mcap"
                shutil.copyfile(path, dst)
                logs[name] = dst
    return logs
