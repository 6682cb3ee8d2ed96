"""The fixed channel names of a U2SA system (DESIGN.md section 3) and their base types.

Services never address each other; they publish to and subscribe from these channels.
A channel's base type is what a receiver decodes unknown extensions as.
"""

from __future__ import annotations

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

BASE_TYPES: dict[str, type] = {
    STATE_INFO: t.StateInformation,
    STATE_ESTIMATE: t.StateInformation,
    GOALS: t.GoalInformation,
    MISSION_STATUS: t.MissionStatus,
    GOAL_REPORT: t.GoalReport,
    MISSION_CMD: t.MissionCommand,
    OBJECTS: t.ObjectDescription,
    WORLD: t.ObjectDescription,
    WORLD_SUMMARY: t.WorldSummary,
    NAV_POINT: t.NavigationPoint,
    ACTUATOR_CMD: t.ActuatorCommand,
    MANUAL_CMD: t.ActuatorCommand,
    RC_MODE: t.RcMode,
    FAILSAFE: t.Failsafe,
    DISCOVERY_REQUEST: t.DiscoveryRequest,
    DISCOVERY_RESPONSE: t.DiscoveryResponse,
    STOP: t.StopCommand,
    CONFIG_REQUEST: t.ConfigRequest,
    CONFIG_CHANGE: t.ConfigChange,
    CONFIG_RESPONSE: t.ConfigResponse,
    HEALTH: t.Health,
    SYSTEM_HEALTH: t.SystemHealth,
}

CONTRACT_CHANNELS = (DISCOVERY_REQUEST, DISCOVERY_RESPONSE, STOP, CONFIG_REQUEST, CONFIG_CHANGE,
                     CONFIG_RESPONSE, HEALTH)


def base_type(channel: str) -> type | None:
    """The declared base type of *channel*, or None for channels without one (RAW.* carry several)."""
    return BASE_TYPES.get(channel)
