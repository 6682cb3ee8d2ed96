"""What a simulation drives: the mission's goals, the a-priori obstacles and the geofence, in local NED.

Read from the same files the mission manager and the world modeler load (their
effective ``mission_file`` and ``objects_file``, relative paths resolved against the
vehicle profile), for the progress line, the summary and the plot.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from u2sa_hw.simulation.summary import Goal
from u2sa_hw.geo import geodetic_to_ned
from u2sa_hw.geofence_parse import profile_fence
from u2sa_hw.services.mission.xml import GLOBAL, load_mission
from u2sa_hw.services.world.model import place_in_world
from u2sa_hw.services.world.xml import load_objects
from u2sa_hw.profile.vehicle import ProfileError, VehicleProfile


@dataclass
class Scenario:
    """The mission (name, loop, goals in file order) and the obstacles of one simulation."""

    mission_name: str
    mission_file: Path
    looping: bool
    goals: list[Goal]
    obstacles: list[Any] = field(default_factory=list)
    objects_file: Path | None = None
    fence: Any = None               # the profile's geofence (u2sa_hw.geofence.Fence), or None


def _service_of_kind(profile: VehicleProfile, kind: str) -> str | None:
    return next((n for n, s in profile.services.items() if s.kind == kind and s.enabled), None)


def _profile_path(profile: VehicleProfile, text: str) -> Path:
    path = Path(text)
    return path if path.is_absolute() or profile.path is None else profile.path.resolve().parent / path


def load_scenario(profile: VehicleProfile, configs: Mapping[str, Mapping[str, Any]], *,
                  mission: Path | None = None) -> Scenario:
    """The scenario of *profile* (with *mission* instead of the configured mission file)."""
    manager = _service_of_kind(profile, "mission_manager")
    if manager is None:
        raise ProfileError(f"{profile.path}: no enabled service of kind mission_manager; a simulation drives "
                           "a mission (add [services.mission] kind = \"mission_manager\")")
    config = configs.get(manager, {})
    if mission is None:
        text = str(config.get("mission_file", "")).strip()
        if not text:
            raise ProfileError(f"{profile.path} [services.{manager}]: no mission_file configured; set it in "
                               f"config/{manager}.toml or pass --mission FILE")
        mission = _profile_path(profile, text)
    spec = load_mission(mission, default_threshold=float(config.get("default_threshold_m", 2.0)))
    loop_setting = str(config.get("loop", "file")).lower()
    looping = spec.loop if loop_setting == "file" else loop_setting == "true"
    goals = []
    for goal in spec.goals:
        values = goal.values
        if goal.frame == GLOBAL and "x" in values:
            north, east, _ = geodetic_to_ned(values["x"], values["y"], origin=profile.origin)
        elif goal.frame == GLOBAL:   # altitude only: the origin's position
            north, east = 0.0, 0.0
        else:
            north, east = values.get("x", 0.0), values.get("y", 0.0)
        goals.append(Goal(goal.uid, north, east, goal.horizontal_threshold))
    scenario = Scenario(spec.name, mission, looping, goals, fence=profile_fence(profile))
    world = _service_of_kind(profile, "world_modeler")
    objects_text = str(configs.get(world, {}).get("objects_file", "")).strip() if world else ""
    if objects_text:
        scenario.objects_file = _profile_path(profile, objects_text)
        radius = float(configs.get(world, {}).get("default_radius_m", 0.0)) if world else 0.0
        objects = load_objects(scenario.objects_file, origin=profile.origin, default_radius=radius)
        scenario.obstacles = [place_in_world(o, pose=None, origin=profile.origin) for o in objects]
    return scenario
