"""Out-of-range and non-finite values over the bus, against a real service process."""

from __future__ import annotations

import json

from conftest import ServiceProcesses, wait_until

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient


def test_out_of_range_values_over_the_bus_are_refused_and_the_file_is_untouched(
        services: ServiceProcesses, bus: BusClient) -> None:
    proc = services.start("state_estimator")
    wait_until(lambda: bus.discover(timeout=0.5, name="state_estimator"), timeout=20, message="the estimator")
    cfg_file = services.workdir / ".u2sa" / "config" / "state_estimator.toml"
    r = services.cli("param", "set", "state_estimator", "sensor_timeout_s", "4.5")
    assert r.returncode == 0, r.stderr
    before = cfg_file.read_bytes()
    for field_name, value, reason in (
            ("health_interval_s", "inf", "field 'health_interval_s' must be a finite number > 0 and <= 60; got inf"),
            ("health_interval_s", "nan", "field 'health_interval_s' must be a finite number > 0 and <= 60; got nan"),
            ("sensor_timeout_s", "-5", "field 'sensor_timeout_s' must be > 0 and <= 3600; got -5.0"),
            ("sensor_timeout_s", "-inf", "field 'sensor_timeout_s' must be a finite number > 0 and <= 3600; got -inf"),
            ("sensor_timeout_s", "-1e3", "field 'sensor_timeout_s' must be > 0 and <= 3600; got -1000.0"),
            # above the bound (issue 23): a rate that spun a core, a timeout that meant never
            ("publish_rate_hz", "1e9", "field 'publish_rate_hz' must be > 0 and <= 1000; got 1000000000.0"),
            ("sensor_timeout_s", "1e308", "field 'sensor_timeout_s' must be > 0 and <= 3600; got 1e+308")):
        r = services.cli("param", "set", "state_estimator", field_name, value)
        # the value reached the service (a leading '-' is not taken for an option) and was refused there;
        # stderr may carry other lines too (a bus warning where lo has no MULTICAST flag), so the refusal
        # is matched as its own line, exactly
        refusals = [line for line in r.stderr.splitlines() if "refused" in line]
        assert r.returncode == 1 and refusals == [f"u2sa: state_estimator refused: {reason}"], r.stderr
        assert cfg_file.read_bytes() == before
    params = json.loads(services.cli("param", "list", "state_estimator", "--json").stdout)
    assert params["sensor_timeout_s"] == 4.5 and params["health_interval_s"] == 1.0
    # still alive and publishing health (an infinite interval used to kill its health thread)
    seen: list[bool] = []
    bus.transport.subscribe(ch.HEALTH, t.Health, lambda _c, msg: seen.append(msg.name == "state_estimator"))
    wait_until(lambda: any(seen), timeout=10, message="a health message after the refusals")
    assert proc.poll() is None


def test_a_service_refuses_to_start_with_an_out_of_range_file(services: ServiceProcesses) -> None:
    cfg_file = services.workdir / ".u2sa" / "config" / "state_estimator.toml"
    cfg_file.parent.mkdir(parents=True)
    cfg_file.write_text("health_interval_s = inf\n")
    r = services.cli("service", "state_estimator", timeout=30)
    assert r.returncode != 0
    assert r.stderr.strip().splitlines()[-1] == ("u2sa: .u2sa/config/state_estimator.toml: field 'health_interval_s' "
                                                 "must be a finite number > 0 and <= 60; got inf; fix it there")
    assert cfg_file.read_text() == "health_interval_s = inf\n"
