"""``u2sa mission``: what the mission manager is doing, the operator's commands to it, and QGroundControl plans.

``status`` prints the next ``MISSION_STATUS``. ``goto``, ``skip``, ``restart`` and
``upload`` send a ``MissionCommand`` on ``MISSION_CMD`` and wait for the mission
manager's acknowledgement: its health (``U2SA_HEALTH``, published at once after a
command) carries ``last_command = "<command> from <sender>: ok"`` or ``"...: refused:
<reason>"``, the sender being this command's own bus name. ``upload`` checks the file
with the mission manager's own parser first, so a mistake is reported with the file,
line and element before anything is sent; a QGroundControl ``.plan`` is converted first
(:mod:`u2sa_hw.services.mission.qgc_plan`, positions about the profile's origin), as
``import`` prints it. ``export`` writes a mission file (by default the one the profile's
mission manager is configured with) as a ``.plan``. Neither import nor export uses the bus.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import tomllib
import uuid
from pathlib import Path
from typing import Any

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.cli.common import add_timeout_option, add_vehicle_option, bus_client, no_answer_error, profile_from

MANAGER_TYPE = "mission_manager"
ACTIONS = ("status", "goto", "skip", "restart", "upload", "import", "export")

HELP = """\
Show the mission manager's status, or change what the vehicle does now:

  status          the mission, its goals and the current one (the next MISSION_STATUS)
  goto UID        make goal UID current now, even before the current one is reached
  skip            leave the current goal without completing it
  restart         start the mission over from its first goal
  upload FILE     replace the whole mission with FILE (checked here first: an error
                  names the file, the line and the element, and nothing is sent);
                  FILE is a mission .xml or a QGroundControl .plan (converted as import does);
                  a goal outside the profile's [geofence] is refused, naming it

QGroundControl plans (no bus; positions through the profile's [vehicle] origin):

  import FILE.plan   print the plan as a mission file (-o FILE.xml writes it): waypoints
                     become local x/y goals, DO_JUMP becomes <next> links (or loop="true"),
                     return-to-launch a goal "home" at the planned home. An item u2sa cannot
                     fly (takeoff, loiter, survey, DO_SET_SERVO ...) is refused with its index,
                     name and the fix. The plan's geofence is taken only when the profile's
                     [geofence] already holds it (plan = "FILE.plan" there); otherwise it is
                     refused, naming that fix, or --ignore-geofence drops it (warned). Every
                     goal must lie inside the profile's fence (docs/geofence.md).
  export FILE.plan   write the mission as a plan QGroundControl opens: the profile's
                     mission manager's mission_file, or --from MISSION.xml

A bus command waits for the mission manager's acknowledgement and prints the resulting
status; it exits 1 with the manager's reason when the command is refused, and 1
when no mission manager acknowledges within --timeout. See docs/core-services.md.
"""


def register(sub: Any) -> None:
    """Add the ``mission`` subcommand."""
    p = sub.add_parser("mission", help="show the mission, go to a goal, skip, restart, upload; QGroundControl plans",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter,
                       epilog="examples:\n  u2sa mission status --vehicle examples/boat/vehicle.toml\n"
                       "  u2sa mission goto dock\n  u2sa mission upload missions/survey.xml\n"
                       "  u2sa mission upload field.plan            (a QGroundControl plan)\n"
                       "  u2sa mission import field.plan -o missions/field.xml\n"
                       "  u2sa mission export harbour.plan --from missions/harbour.xml")
    p.add_argument("action", choices=ACTIONS, help="what to do (see above)")
    p.add_argument("target", nargs="?", metavar="UID|FILE",
                   help="the goal of goto; the mission file of upload; the .plan of import and export")
    p.add_argument("--json", action="store_true", help="print the resulting status as JSON")
    p.add_argument("--ignore-geofence", action="store_true",
                   help="import/upload a plan whose geofence the profile does not hold: drop the plan's fence "
                        "(the vehicle enforces only its profile's [geofence])")
    p.add_argument("-o", "--output", metavar="FILE.xml", help="import: write the mission here (default: print it)")
    p.add_argument("--from", dest="source", metavar="MISSION.xml",
                   help="export: the mission file (default: the profile's mission manager's mission_file)")
    p.add_argument("--force", action="store_true", help="import -o, export: replace an existing file")
    add_vehicle_option(p)
    add_timeout_option(p, 5.0)
    p.set_defaults(func=cmd_mission)


def _warn(text: str) -> None:
    print(f"u2sa: warning: {text}", file=sys.stderr)


def _origin(args: Any, verb: str, what: str) -> Any:
    """The profile's origin, which a plan's latitudes and longitudes go through; CliError if it sets none."""
    from u2sa_hw.cli import CliError

    profile = profile_from(args)
    vehicle = profile.raw.get("vehicle", {}) if profile.path else {}
    if not isinstance(vehicle, dict) or "origin" not in vehicle:
        which = f"{profile.path} sets none" if profile.path else \
            "there is no vehicle profile (--vehicle, $U2SA_VEHICLE or /etc/u2sa/vehicle.toml)"
        raise CliError(f"mission {verb}: {what} holds latitudes and longitudes, which become local x/y about the "
                       f"vehicle profile's [vehicle] origin, and {which}: add origin = {{ lat = ..., lon = ..., "
                       "alt = ... } to the profile, or pass --vehicle")
    return profile.origin


def plan_to_xml(path: Path, data: bytes, args: Any, verb: str) -> str:
    """The .plan at *path* (its bytes *data*) as mission XML; warnings on stderr; CliError on any problem."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.services.mission.qgc_plan import PlanError, load_plan_text, plan_to_mission
    from u2sa_hw.services.mission.xml import mission_to_xml

    from u2sa_hw.cli.mission_fence import check_goals_in_fence, plan_fence_warnings

    origin = _origin(args, verb, str(path))
    try:
        plan = load_plan_text(data, source=str(path))
        spec, warnings = plan_to_mission(plan, source=str(path), origin=origin)
    except PlanError as exc:
        raise CliError(f"mission {verb}: {exc}" + ("; nothing was sent" if verb == "upload" else "")) from None
    profile = profile_from(args)
    warnings += plan_fence_warnings(plan, path=path, profile=profile, origin=origin, verb=verb,
                                    ignore=bool(getattr(args, "ignore_geofence", False)))
    for warning in warnings:
        _warn(warning)
    text = mission_to_xml(spec, comment=f"from {path.name} by u2sa mission import: x north, y east (m) about the "
                                        f"origin lat {origin.lat}, lon {origin.lon}")
    check_goals_in_fence(text, source=str(path), profile=profile, verb=verb)
    return text


def read_mission_file(path: Path, args: Any = None) -> str:
    """The text of mission file *path* (a .plan converted), checked with the mission manager's parser; CliError."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.services.mission.qgc_plan import looks_like_plan
    from u2sa_hw.services.mission.xml import parse_mission
    from u2sa_hw.services.mission.xmltree import XmlFileError

    try:
        data = path.read_bytes()
    except OSError as exc:
        raise CliError(f"mission upload: {path}: cannot read: {exc.strerror or exc}") from None
    if looks_like_plan(path, data):
        text = plan_to_xml(path, data, args or argparse.Namespace(vehicle=None), "upload")
    else:
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise CliError(f"mission upload: {path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    try:
        # The manager fills a missing <threshold> from its own default, so any default checks the same rules.
        spec = parse_mission(text, source=str(path), default_threshold=1.0)
    except XmlFileError as exc:
        raise CliError(f"mission upload: {exc}; nothing was sent") from None
    if not spec.goals:
        raise CliError(f"mission upload: {path}: no goals; nothing was sent")
    if not looks_like_plan(path, data):   # a plan's goals were checked as it was converted
        from u2sa_hw.cli.mission_fence import check_goals_in_fence

        check_goals_in_fence(text, source=str(path), profile=profile_from(args or argparse.Namespace(vehicle=None)),
                             verb="upload")
    return text


def _write(path: Path, text: str, *, force: bool, verb: str) -> None:
    from u2sa_hw.cli import CliError

    if path.exists() and not force:
        raise CliError(f"mission {verb}: {path} exists; pass --force to replace it")
    try:
        path.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise CliError(f"mission {verb}: {path}: cannot write: {exc.strerror or exc}") from None


def cmd_import(args: Any) -> int:
    """``u2sa mission import FILE.plan [-o FILE.xml]``."""
    from u2sa_hw.cli import CliError

    path = Path(args.target)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise CliError(f"mission import: {path}: cannot read: {exc.strerror or exc}") from None
    text = plan_to_xml(path, data, args, "import")
    if not args.output:
        sys.stdout.write(text)
        return 0
    _write(Path(args.output), text, force=args.force, verb="import")
    print(f"{args.output}: {text.count('<waypoint>')} goals from {path}")
    return 0


def _service_setting(profile: Any, spec: Any, key: str, default: Any) -> Any:
    """A setting where the service reads it: its config file, then the profile's settings, then *default*."""
    try:
        config = tomllib.loads(spec.config_path.read_text(encoding="utf-8")) if spec.config_path.is_file() else {}
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        config = {}
    return config.get(key, spec.settings.get(key, default))


def _configured_mission(profile: Any) -> Path:
    from u2sa_hw.cli import CliError

    managers = [s for s in profile.services.values() if s.kind == MANAGER_TYPE and s.enabled]
    where = profile.path or "the default profile (there is no --vehicle, $U2SA_VEHICLE or /etc/u2sa/vehicle.toml)"
    if len(managers) != 1:
        names = f" ({', '.join(s.name for s in managers)})" if managers else ""
        raise CliError(f"mission export: {where} has {len(managers) or 'no'} mission_manager service{names}: "
                       "give the mission file with --from MISSION.xml")
    value = _service_setting(profile, managers[0], "mission_file", "")
    path = profile.resolve_path(value) if isinstance(value, str) else None
    if path is None:
        raise CliError(f"mission export: service {managers[0].name} has no mission_file (an uploaded mission is "
                       "not kept on disk): give the mission file with --from MISSION.xml")
    return path


def cmd_export(args: Any) -> int:
    """``u2sa mission export FILE.plan [--from MISSION.xml]``."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.services.mission.qgc_plan import (MAV_TYPE_GROUND_ROVER, MAV_TYPE_SURFACE_BOAT, PlanError,
                                                   mission_to_plan, plan_json)
    from u2sa_hw.services.mission.xml import load_mission
    from u2sa_hw.services.mission.xmltree import XmlFileError

    out = Path(args.target)
    if out.suffix.lower() != ".plan":
        raise CliError(f"mission export: {out}: the file to write is a QGroundControl plan: name it *.plan "
                       "(the mission to export goes in --from)", 2)
    profile = profile_from(args)
    source = Path(args.source) if args.source else _configured_mission(profile)
    origin = _origin(args, "export", str(source))
    try:
        spec = load_mission(source, default_threshold=0.0)   # 0: no <threshold>, the plan's radius 0
        simulation = profile.raw.get("simulation", {})
        boat = isinstance(simulation, dict) and simulation.get("model") == "twin_thruster"
        planners = [s for s in profile.services.values() if s.kind == "path_planner" and s.enabled]
        speed = _service_setting(profile, planners[0], "cruise_speed_m_s", 1.0) if planners else 1.0
        speed = float(speed) if isinstance(speed, (int, float)) and not isinstance(speed, bool) and speed > 0 else 1.0
        plan, warnings = mission_to_plan(spec, origin=origin, cruise_speed=speed,
                                         vehicle_type=MAV_TYPE_SURFACE_BOAT if boat else MAV_TYPE_GROUND_ROVER)
    except (XmlFileError, PlanError) as exc:
        raise CliError(f"mission export: {exc}") from None
    for warning in warnings:
        _warn(warning)
    _write(out, plan_json(plan), force=args.force, verb="export")
    print(f"{out}: mission '{spec.name}' from {source}, {len(spec.goals)} goals in "
          f"{len(plan['mission']['items'])} plan items")
    return 0


class MissionListener:
    """The latest MISSION_STATUS and the mission manager's acknowledgement of one sender's command."""

    def __init__(self, bus: Any, sender: str) -> None:
        self.sender = sender
        self.status: t.MissionStatus | None = None
        self.ack: tuple[str, str] | None = None   # (mission manager's name, last_command text)
        self.got_status = threading.Event()
        self.got_ack = threading.Event()
        self._lock = threading.Lock()
        self._subs = [bus.transport.subscribe(ch.MISSION_STATUS, t.MissionStatus, self._on_status),
                      bus.transport.subscribe(ch.HEALTH, t.Health, self._on_health)]
        self._bus = bus

    def close(self) -> None:
        """Stop listening."""
        for sub in self._subs:
            self._bus.transport.unsubscribe(sub)

    def _on_status(self, _channel: str, msg: t.MissionStatus) -> None:
        with self._lock:
            self.status = msg
        self.got_status.set()

    def _on_health(self, _channel: str, msg: t.Health) -> None:
        if msg.service_type != MANAGER_TYPE:
            return
        text = next((kv.value for kv in msg.details if kv.key == "last_command"), "")
        if f" from {self.sender}: " in text:
            with self._lock:
                self.ack = (msg.name, text)
            self.got_ack.set()


def status_dict(st: t.MissionStatus) -> dict[str, Any]:
    """A MissionStatus as JSON-ready data."""
    return {"mission": st.mission_name, "current_uid": st.current_uid, "current_index": st.current_index,
            "goals": list(st.goal_uids), "finished": st.finished, "looping": st.looping,
            "source": st.header.source}


def status_lines(st: t.MissionStatus) -> list[str]:
    """The status for people: the mission, then one line per goal with the current one marked."""
    state = "finished" if st.finished else f"goal {st.current_index + 1} of {st.num_goals}: {st.current_uid}"
    lines = [f"mission '{st.mission_name}' ({st.header.source or '?'}): {state}"
             + (", looping" if st.looping else "")]
    for i, uid in enumerate(st.goal_uids):
        lines.append(f"  {'>' if (uid == st.current_uid and not st.finished) else ' '} {i + 1:2d} {uid}")
    return lines


def _print_status(st: t.MissionStatus, *, as_json: bool) -> None:
    if as_json:
        print(json.dumps(status_dict(st), indent=2))
    else:
        print("\n".join(status_lines(st)))


def cmd_mission(args: Any) -> int:
    """Run ``u2sa mission ACTION``; CliError (exit 1) on a refusal or without an answer."""
    from u2sa_hw.cli import CliError

    action = args.action
    takes = {"goto": "goal UID", "upload": "mission FILE", "import": "FILE.plan to import",
             "export": "FILE.plan to write"}
    if action in takes and not args.target:
        raise CliError(f"mission {action}: give the {takes[action]}", 2)
    if action not in takes and args.target:
        raise CliError(f"mission {action} takes no argument (got {args.target!r})", 2)
    misplaced = [flag for flag, value, verbs in (("--ignore-geofence", args.ignore_geofence, ("import", "upload")),
                                                  ("-o/--output", args.output, ("import",)),
                                                  ("--from", args.source, ("export",)),
                                                  ("--force", args.force, ("import", "export")))
                 if value and action not in verbs]
    if misplaced:
        raise CliError(f"mission {action}: {misplaced[0]} is not an option of {action}", 2)
    if action == "import":
        return cmd_import(args)
    if action == "export":
        return cmd_export(args)
    if args.timeout <= 0:
        raise CliError("mission: --timeout must be > 0 seconds", 2)
    mission_xml = read_mission_file(Path(args.target), args) if action == "upload" else ""
    sender = f"u2sa-mission-{os.getpid()}-{uuid.uuid4().hex[:6]}"
    with bus_client(args, name=sender) as bus:
        listener = MissionListener(bus, sender)
        try:
            return _run_action(args, bus, listener, action=action, mission_xml=mission_xml)
        finally:
            listener.close()


def _run_action(args: Any, bus: Any, listener: MissionListener, *, action: str, mission_xml: str) -> int:
    from u2sa_hw.cli import CliError

    if action == "status":
        if not listener.got_status.wait(args.timeout):
            raise no_answer_error(args, f"mission status: no MISSION_STATUS within {args.timeout:g} s on "
                                        f"{bus.transport.url}; is a mission manager running (u2sa services lists "
                                        "the live ones)?")
        _print_status(listener.status, as_json=args.json)
        return 0
    cmd = t.MissionCommand()
    cmd.command = action
    cmd.uid = args.target if action == "goto" else ""
    cmd.mission_xml = mission_xml
    bus.publish(ch.MISSION_CMD, cmd)
    if not listener.got_ack.wait(args.timeout):
        raise no_answer_error(args, f"mission {action}: no mission manager acknowledged within {args.timeout:g} s "
                                    f"on {bus.transport.url}; is one running (u2sa services lists the live ones)? "
                                    "Check with u2sa mission status before sending again")
    manager, text = listener.ack
    outcome = text.split(f" from {listener.sender}: ", 1)[1]
    if outcome != "ok":
        raise CliError(f"mission {action}: {manager} {outcome}")
    # The manager publishes the changed mission before its acknowledgement.
    if listener.status is not None:
        _print_status(listener.status, as_json=args.json)
    else:
        print(f"{manager}: {action} done")
    return 0
