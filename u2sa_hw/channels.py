"""The fixed channel names of a U2SA system (DESIGN.md section 3) and their base types.

Services never address each other; they publish to and subscribe from these channels.
A channel's base type is what a receiver decodes unknown extensions as.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping

from u2sa_hw import lcmtypes as t

STATE_INFO = "STATE_INFO"            # proprioceptive sensors -> state estimator
STATE_ESTIMATE = "STATE_ESTIMATE"    # state estimator -> everyone
GOALS = "GOALS"                      # mission manager -> path planner
MISSION_STATUS = "MISSION_STATUS"    # mission manager summary
GOAL_REPORT = "GOAL_REPORT"          # path planner -> mission manager
MISSION_CMD = "MISSION_CMD"          # operator -> mission manager
OBJECTS = "OBJECTS"                  # exteroceptive sensors -> world modeler
WORLD = "WORLD"                      # world modeler -> path planner
WORLD_SUMMARY = "WORLD_SUMMARY"
NAV_POINT = "NAV_POINT"              # path planner -> control system
ACTUATOR_CMD = "ACTUATOR_CMD"        # control system -> actuators (obeyed only while autonomy is granted)
MANUAL_CMD = "MANUAL_CMD"            # RC mux (the pilot's sticks through the manual mixer) -> actuators
RC_MODE = "RC_MODE"                  # RC mux driver -> control system, HSM
FAILSAFE = "FAILSAFE"                # HSM -> actuators, RC mux
DISCOVERY_REQUEST = "U2SA_DISCOVERY"
DISCOVERY_RESPONSE = "U2SA_DISCOVERY_REPLY"
STOP = "U2SA_STOP"
CONFIG_REQUEST = "U2SA_CONFIG"
CONFIG_CHANGE = "U2SA_CONFIG_SET"
CONFIG_RESPONSE = "U2SA_CONFIG_REPLY"
HEALTH = "U2SA_HEALTH"
SYSTEM_HEALTH = "U2SA_SYSTEM_HEALTH"
RAW_PREFIX = "RAW."                  # RAW.<device>: raw device I/O for recording/replay

class _ChannelTypes(Mapping[str, type]):
    """Channel -> base type, each type loaded when first looked up (a process loads only the types it uses)."""

    def __init__(self, names: dict[str, str]) -> None:
        self._names = names

    def __getitem__(self, channel: str) -> type:
        return getattr(t, self._names[channel])

    def __iter__(self) -> Iterator[str]:
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)


BASE_TYPES: Mapping[str, type] = _ChannelTypes({
    STATE_INFO: "StateInformation",
    STATE_ESTIMATE: "StateInformation",
    GOALS: "GoalInformation",
    MISSION_STATUS: "MissionStatus",
    GOAL_REPORT: "GoalReport",
    MISSION_CMD: "MissionCommand",
    OBJECTS: "ObjectDescription",
    WORLD: "ObjectDescription",
    WORLD_SUMMARY: "WorldSummary",
    NAV_POINT: "NavigationPoint",
    ACTUATOR_CMD: "ActuatorCommand",
    MANUAL_CMD: "ActuatorCommand",
    RC_MODE: "RcMode",
    FAILSAFE: "Failsafe",
    DISCOVERY_REQUEST: "DiscoveryRequest",
    DISCOVERY_RESPONSE: "DiscoveryResponse",
    STOP: "StopCommand",
    CONFIG_REQUEST: "ConfigRequest",
    CONFIG_CHANGE: "ConfigChange",
    CONFIG_RESPONSE: "ConfigResponse",
    HEALTH: "Health",
    SYSTEM_HEALTH: "SystemHealth",
})

CONTRACT_CHANNELS = (DISCOVERY_REQUEST, DISCOVERY_RESPONSE, STOP, CONFIG_REQUEST, CONFIG_CHANGE,
                     CONFIG_RESPONSE, HEALTH)


def base_type(channel: str) -> type | None:
    """The declared base type of *channel*, or None for channels without one (RAW.* carry several)."""
    return BASE_TYPES.get(channel)
