"""The one resolver of a profile's devices (u2sa_hw.profile.devices.resolve_devices) in each of its modes.

Drivers, ``u2sa check``, install, the mock launcher and replay all read a profile's devices through it
(docs/ports.md): strict (a mistake is one error naming the table and the fix), lenient (the bad devices
left out with their services, the rest resolved) and on a recorded profile's raw TOML data (replay).
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from u2sa_hw.check.lenient import readable_configs
from u2sa_hw.ports.address import AddressError
from u2sa_hw.profile.devices import device_address, profile_devices, resolve_devices
from u2sa_hw.profile.loader import load_profile
from u2sa_hw.profile.vehicle import ProfileError

PROFILE = """
[vehicle]
name = "r"

[services.gps]
kind = "gps_nmea"
settings = { device = "gnss" }

[services.wheels]
kind = "odrive_can"

[devices.gnss]
address = "serial:///dev/ttyUSB0?baud=4800"

[devices.wheels]
address = "can://socketcan/can1?bitrate=250000"
"""
BAD_WHEELS = PROFILE.replace("can://socketcan/can1?bitrate=250000", "can://socketcan/can1?bitrat=250000")


def _load(tmp_path: Path, text: str):
    (tmp_path / "vehicle.toml").write_text(text)
    return load_profile(tmp_path / "vehicle.toml")


def test_strict_gives_every_device_with_its_service(tmp_path: Path) -> None:
    resolved = resolve_devices(_load(tmp_path, PROFILE))
    assert {n: (e.address.kind, e.service) for n, e in resolved.entries.items()} == {
        "gnss": ("serial", "gps"), "wheels": ("can", "wheels")}
    assert resolved.users == {"gnss": ("gps",), "wheels": ("wheels",)}
    assert resolved.entries == profile_devices(_load(tmp_path, PROFILE))
    assert device_address(_load(tmp_path, PROFILE), "gnss") == resolved.entries["gnss"].address


def test_strict_refuses_a_bad_address_naming_the_table(tmp_path: Path) -> None:
    with pytest.raises(ProfileError, match=r"\[devices.wheels\]: .*unknown parameter 'bitrat'"):
        resolve_devices(_load(tmp_path, BAD_WHEELS))


def test_lenient_leaves_the_bad_device_and_its_service_out_and_resolves_the_rest(tmp_path: Path) -> None:
    profile = _load(tmp_path, BAD_WHEELS)
    resolved = resolve_devices(profile, configs=readable_configs(profile), strict=False)
    assert resolved.bad == {"wheels"} and resolved.error is None
    assert set(resolved.entries) == {"gnss"}
    assert resolved.profile is not None and "wheels" not in resolved.profile.devices
    assert not resolved.profile.services["wheels"].enabled and resolved.profile.services["gps"].enabled


def test_lenient_keeps_what_stops_the_rest_instead_of_raising(tmp_path: Path) -> None:
    text = PROFILE.replace('settings = { device = "gnss" }', 'settings = { device = "gnsss" }')
    profile = _load(tmp_path, text)
    resolved = resolve_devices(profile, configs=readable_configs(profile), strict=False)
    assert resolved.entries == {} and isinstance(resolved.error, ProfileError)
    assert "device 'gnsss' of service 'gps' has no address" in str(resolved.error)


def test_a_recorded_profile_is_read_from_its_raw_data() -> None:
    data = tomllib.loads(BAD_WHEELS)
    configs = {"gps": {"device": "gnss"}, "wheels": {}}
    resolved = resolve_devices(data, configs=configs, strict=False)
    assert resolved.users["gnss"] == ("gps",) and resolved.users["gps"] == ("gps",)   # its own name too
    assert resolved.entries["gnss"].address.kind == "serial" and resolved.entries["gnss"].service == "gps"
    assert resolved.bad == {"wheels"} and "wheels" not in resolved.entries
    with pytest.raises(AddressError, match="wheels"):
        resolve_devices(data, configs=configs)
    with pytest.raises(AddressError, match=r"no address: add \[devices.gps\] address"):
        device_address(data, "gps")


def test_install_leaves_an_old_form_service_out_and_reads_the_rest(tmp_path: Path) -> None:
    """A service still given the old form is the services check's error (naming the new form); install reads
    the other devices past it (skip_old_form), and the strict read refuses it."""
    from u2sa_hw.config.fields import ConfigError

    text = PROFILE.replace('settings = { device = "gnss" }', 'settings = { device = "gnss" }\nconfig = "gps.toml"')
    (tmp_path / "gps.toml").write_text('port = "/dev/ttyUSB0"\n')
    profile = _load(tmp_path, text)
    with pytest.raises(ConfigError, match="'port' is the old form"):
        resolve_devices(profile)
    resolved = resolve_devices(profile, skip_old_form=True)
    assert resolved.entries["wheels"].service == "wheels" and not resolved.entries["gnss"].used
