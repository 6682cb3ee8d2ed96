"""``u2sa mission``: what the mission manager is doing, and the operator's commands to it.

``status`` prints the next ``MISSION_STATUS``. ``goto``, ``skip``, ``restart`` and
``upload`` send a ``MissionCommand`` on ``MISSION_CMD`` and wait for the mission
manager's acknowledgement: its health (``U2SA_HEALTH``, published at once after a
command) carries ``last_command = "<command> from <sender>: ok"`` or ``"...: refused:
<reason>"``, the sender being this command's own bus name. ``upload`` checks the file
with the mission manager's own parser first, so a mistake is reported with the file,
line and element before anything is sent.
"""

from __future__ import annotations

import argparse
import json
import os
import threading
import uuid
from pathlib import Path
from typing import Any

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.cli.common import add_timeout_option, add_vehicle_option, bus_client, no_answer_error

MANAGER_TYPE = "mission_manager"
ACTIONS = ("status", "goto", "skip", "restart", "upload")

HELP = """\
Show the mission manager's status, or change what the vehicle does now:

  status          the mission, its goals and the current one (the next MISSION_STATUS)
  goto UID        make goal UID current now, even before the current one is reached
  skip            leave the current goal without completing it
  restart         start the mission over from its first goal
  upload FILE     replace the whole mission with FILE (checked here first: an error
                  names the file, the line and the element, and nothing is sent)

A command waits for the mission manager's acknowledgement and prints the resulting
status; it exits 1 with the manager's reason when the command is refused, and 1
when no mission manager acknowledges within --timeout. See docs/core-services.md.
"""


def register(sub: Any) -> None:
    """Add the ``mission`` subcommand."""
    p = sub.add_parser("mission", help="show the mission, go to a goal, skip, restart, upload a mission",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter,
                       epilog="examples:\n  u2sa mission status --vehicle examples/boat/vehicle.toml\n"
                       "  u2sa mission goto dock\n  u2sa mission upload missions/survey.xml")
    p.add_argument("action", choices=ACTIONS, help="what to do (see above)")
    p.add_argument("target", nargs="?", metavar="UID|FILE", help="the goal of goto, the mission file of upload")
    p.add_argument("--json", action="store_true", help="print the resulting status as JSON")
    add_vehicle_option(p)
    add_timeout_option(p, 5.0)
    p.set_defaults(func=cmd_mission)


def read_mission_file(path: Path) -> str:
    """The text of mission file *path*, checked with the mission manager's parser; CliError on any problem."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.services.mission.xml import parse_mission
    from u2sa_hw.services.mission.xmltree import XmlFileError

    try:
        text = path.read_bytes().decode("utf-8")
    except OSError as exc:
        raise CliError(f"mission upload: {path}: cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise CliError(f"mission upload: {path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    try:
        # The manager fills a missing <threshold> from its own default, so any default checks the same rules.
        spec = parse_mission(text, source=str(path), default_threshold=1.0)
    except XmlFileError as exc:
        raise CliError(f"mission upload: {exc}; nothing was sent") from None
    if not spec.goals:
        raise CliError(f"mission upload: {path}: no goals; nothing was sent")
    return text


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
    if action in ("goto", "upload") and not args.target:
        raise CliError(f"mission {action}: give the {'goal UID' if action == 'goto' else 'mission FILE'}", 2)
    if action not in ("goto", "upload") and args.target:
        raise CliError(f"mission {action} takes no argument (got {args.target!r})", 2)
    if args.timeout <= 0:
        raise CliError("mission: --timeout must be > 0 seconds", 2)
    mission_xml = read_mission_file(Path(args.target)) if action == "upload" else ""
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
