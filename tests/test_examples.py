"""The example vehicles under examples/: every profile, per-service config, mission and objects file loads.

Each service is built as ``u2sa service`` builds it (its kind from the registry, its
config file over the profile's settings) and asked, field by field, whether its own
validator accepts the value it has, so a config that a service would refuse at start or
over the bus fails here, naming the example, the service and the field.
"""

from __future__ import annotations

import logging
import tomllib
from pathlib import Path
from typing import Any

import pytest
from conftest import REPO

from u2sa_hw.registry import resolve_kind
from u2sa_hw.services.mission.xml import load_mission
from u2sa_hw.services.world.xml import load_objects
from u2sa_hw.simulation.profile import effective_configs
from u2sa_hw.simulation.scenario import load_scenario
from u2sa_hw.bus.transport import Transport
from u2sa_hw.profile.vehicle import VehicleProfile
from u2sa_hw.profile.loader import load_profile

EXAMPLES = sorted((REPO / "examples").glob("*/vehicle.toml"))


def test_there_are_examples_to_check() -> None:
    assert {p.parent.name for p in EXAMPLES} >= {"ground_vehicle", "boat"}


@pytest.fixture(params=EXAMPLES, ids=lambda p: p.parent.name)
def profile(request: pytest.FixtureRequest) -> VehicleProfile:
    return load_profile(request.param)


def test_every_kind_resolves_and_every_config_file_belongs_to_a_service(profile: VehicleProfile) -> None:
    for name, spec in profile.services.items():
        assert resolve_kind(spec.kind), f"{profile.path}: [services.{name}] kind {spec.kind!r}"
    config_files = {p.resolve() for p in profile.config_dir.glob("*.toml")}
    used = {spec.config_path.resolve() for spec in profile.services.values()}
    assert config_files - used == set(), f"{profile.config_dir}: config files no service of the profile reads"
    assert used <= config_files, f"services without a config file in {profile.config_dir}: {used - config_files}"


def test_every_config_file_is_valid_toml_and_commented(profile: VehicleProfile) -> None:
    for spec in profile.services.values():
        text = spec.config_path.read_text()
        tomllib.loads(text)
        assert text.lstrip().startswith("#"), f"{spec.config_path}: start with a comment saying what it configures"


def _build(cls: type, name: str, profile: VehicleProfile, spec: Any, transport: Transport) -> Any:
    return cls(name, profile=profile, config_path=spec.config_path, settings=spec.settings, transport=transport,
               logger=logging.getLogger(f"examples.{profile.name}.{name}"))


def test_every_service_accepts_its_config(profile: VehicleProfile, lcm_url: str,
                                          caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING)
    for name, spec in profile.services.items():
        cls = resolve_kind(spec.kind)
        transport = Transport(lcm_url, name=name)
        try:
            service = _build(cls, name, profile, spec, transport)   # several kinds check their config here
            for field_name, _type, value in service.config.enumerate():
                problem = service.validate_config(field_name, value)
                assert problem is None, f"{spec.config_path} ({spec.kind}): {field_name} = {value!r}: {problem}"
        finally:
            transport.stop()
    unknown = [r.getMessage() for r in caplog.records if "unknown config field" in r.getMessage()]
    assert unknown == [], f"{profile.path}: fields no service declares: {unknown}"


def test_mission_and_objects_files_load(profile: VehicleProfile) -> None:
    configs = effective_configs(profile)
    scenario = load_scenario(profile, configs)   # the files the mission manager and world modeler are given
    assert scenario.goals and scenario.obstacles
    mission = load_mission(scenario.mission_file)
    assert len(mission.goals) == len(scenario.goals) and all(g.horizontal_threshold > 0 for g in mission.goals)
    assert scenario.objects_file is not None
    assert len(load_objects(scenario.objects_file, origin=profile.origin)) == len(scenario.obstacles)


@pytest.mark.parametrize("path", sorted((REPO / "examples").glob("*/*.xml")), ids=lambda p: f"{p.parent.name}/{p.name}")
def test_every_example_xml_file_parses(path: Path) -> None:
    head = path.read_text()
    if "<mission" in head:
        assert load_mission(path, default_threshold=2.0).goals
    else:
        assert "<world" in head
        assert load_objects(path, origin=load_profile(path.parent / "vehicle.toml").origin)
