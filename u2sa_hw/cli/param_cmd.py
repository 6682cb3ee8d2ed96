"""``u2sa param list|get|set|save|load``: the services' configuration over the bus (requirement C7).

``save`` and ``load`` are parameter files (ArduPilot's .param, ``ros2 param dump``/``load``):
every service's fields in one TOML file, written from the bus and applied back, all or
nothing per service (u2sa_hw/config/param_file.py has the format and the checks).

A service name nobody on the bus answers to fails after one discovery round, with a
did-you-mean from the names that did answer, instead of waiting for an answer that cannot come.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import re
import os
import sys
import tempfile
import tomllib
from datetime import datetime
from pathlib import Path
from typing import Any

from u2sa_hw.cli.common import add_timeout_option, add_vehicle_option, bus_client, no_answer_error, profile_from


_NEGATIVE_LITERAL = re.compile(r"^-(?:\d[\d_]*(?:\.\d[\d_]*)?(?:[eE][+-]?\d+)?|\.\d+|inf|nan)$")


def register(sub: Any) -> None:
    """Add the ``param`` subcommand group."""
    p = sub.add_parser("param", help="list, get, set, save or load the services' config over the bus",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Read and change a running service's typed config. A change is checked "
                       "against the field's type, allowed values and range by the service (a value out of range, or "
                       "inf/nan where the field needs a finite number, is refused with the bound and the value) "
                       "and written to its TOML file atomically; a refused change leaves the file untouched. "
                       "VALUE is a TOML literal: 42, 2.5, -5, true, \"text\". For a text field "
                       "a quoted string gives its contents and anything else is taken as it is, so "
                       "mode passthrough and mode '\"passthrough\"' both set passthrough. "
                       "save writes every service's fields (or the named ones') to a TOML parameter file; load "
                       "prints how a file differs from the services and applies it, all or nothing per service. "
                       "A service name that is not on the bus fails after one discovery round, naming the "
                       "services that are (with a did-you-mean).",
                       epilog="examples:\n  u2sa param list estimator --json\n"
                       "  u2sa param set gps baudrate 38400\n  u2sa param set estimator mode passthrough\n"
                       "  u2sa param set estimator log_level debug\n"
                       "  u2sa param set compass declination_deg -6.5   (a negative value needs no quoting)\n"
                       "  u2sa param set estimator log_level '\"\"'     (empty: the profile's level)\n"
                       "  u2sa param save rover.params.toml            (every service on the bus)\n"
                       "  u2sa param save est.toml estimator           (one service)\n"
                       "  u2sa param load rover.params.toml --dry-run  (the differences only)\n"
                       "  u2sa param load rover.params.toml")
    psub = p.add_subparsers(dest="param_command", metavar="ACTION", required=True)
    lp = psub.add_parser("list", help="every field with its type and value")
    lp.add_argument("service")
    lp.add_argument("--json", action="store_true", help="print an object name -> value")
    gp = psub.add_parser("get", help="one field's value")
    gp.add_argument("service")
    gp.add_argument("field")
    sp = psub.add_parser("set", help="change one field (persisted); exits 1 with the reason when refused")
    sp.add_argument("service")
    sp.add_argument("field")
    sp.add_argument("value", help="a TOML literal (42, 2.5, -5, -inf, true, \"text\"); for a text field a quoted "
                    "string gives its contents and a bare word is itself; a value starting with '-' (a negative "
                    "number, -inf) is a value, not an option")
    # argparse takes "-inf" and "-1e3" for options (only "-5" and "-.5" look like numbers to it); this
    # parser has no option that looks like a number, so every TOML number literal is a value.
    sp._negative_number_matcher = _NEGATIVE_LITERAL
    for q in (lp, gp, sp):
        add_vehicle_option(q)
        add_timeout_option(q, 2.0)
        q.set_defaults(func=cmd_param)
    svp = psub.add_parser("save", help="write every service's fields (or the named services') to a TOML file",
                          description="Ask every service on the bus (or only SERVICE...) for its config and write "
                          "a TOML parameter file: a header comment (vehicle, date), then per service a table "
                          "[NAME] with its kind and [NAME.params] with its typed values. Written atomically; "
                          "nothing is written when a service does not answer. FILE '-' prints it.")
    svp.add_argument("file", metavar="FILE")
    svp.add_argument("services", nargs="*", metavar="SERVICE", help="only these services (default: all on the bus)")
    lop = psub.add_parser("load", help="print how a parameter file differs from the services, then apply it",
                          description="Compare FILE (as param save writes it) with what the services on the bus "
                          "report, print every difference (service.field: current -> new), then apply them, all "
                          "or nothing per service: a change the service refuses rolls back the ones already "
                          "applied to it. Before anything changes, a service not on the bus, a field it does not "
                          "have, a value of the wrong type, not one of its choices or out of its range, or a "
                          "field not changed over the bus, is refused with the file and line, and nothing is "
                          "applied. Fields the file leaves out are left as they are.")
    lop.add_argument("file", metavar="FILE")
    lop.add_argument("services", nargs="*", metavar="SERVICE", help="only these services' tables (default: all)")
    lop.add_argument("--dry-run", action="store_true", help="print the differences and change nothing")
    for q in (svp, lop):
        add_vehicle_option(q)
        add_timeout_option(q, 2.0)
    svp.set_defaults(func=cmd_param_save)
    lop.set_defaults(func=cmd_param_load)


def _value(field: Any) -> Any:
    try:
        return tomllib.loads(f"v = {field.value}")["v"]
    except tomllib.TOMLDecodeError:
        return field.value


def cmd_param(args: Any) -> int:
    """Dispatch ``param list/get/set``."""
    from u2sa_hw.cli import CliError

    with bus_client(args) as bus:
        require_service(args, bus, args.service)
        if args.param_command == "set":
            resp = bus.set_config(args.service, args.field, args.value, timeout=args.timeout)
        else:
            resp = bus.get_config(args.service, timeout=args.timeout)
    if resp is None:
        raise no_answer_error(args, f"service '{args.service}' did not answer within {args.timeout:g} s "
                              "(u2sa services lists the live ones)")
    if not resp.ok:
        raise CliError(f"{args.service} refused: {resp.error}")
    if resp.error:  # accepted with a warning (saved, but its directory could not be synced)
        print(f"u2sa: warning: {args.service}: {resp.error}", file=sys.stderr)
    fields = {f.name: f for f in resp.fields}
    if args.param_command == "list":
        if args.json:
            print(json.dumps({n: _value(f) for n, f in fields.items()}, indent=2))
        else:
            for n, f in fields.items():
                print(f"{n:28} {f.type_name:6} {f.value}")
        return 0
    f = fields.get(args.field)
    if f is None:
        raise CliError(f"{args.service} has no config field '{args.field}' (known: {', '.join(sorted(fields))})")
    print(f.value)
    return 0


def require_service(args: Any, bus: Any, name: str) -> Any:
    """*name*'s discovery answer; when it is not there, a CliError naming the services on the bus (a did-you-mean)."""
    from u2sa_hw.bus.client import unknown_service_text
    from u2sa_hw.cli import CliError

    found, names = bus.find_service(name, timeout=args.timeout)
    if found is not None:
        return found
    if names:
        raise CliError(unknown_service_text(name, names))
    raise no_answer_error(args, f"service '{name}' did not answer: no service answered discovery within "
                          f"{args.timeout:g} s (are services running, and on the same LCM URL and bus key?)")


def _kind_of(profile: Any, name: str, service_type: str) -> str:
    """The kind of service *name*: the profile's, else its service type or its name when that is a kind, else ""."""
    from u2sa_hw.registry import known_kinds

    spec = profile.services.get(name)
    if spec is not None:
        return spec.kind
    kinds = known_kinds()
    return next((k for k in (service_type, name) if k in kinds), "")


def _live(args: Any, bus: Any, answers: list[Any]) -> dict[str, Any]:
    """name -> LiveService for every discovery answer in *answers*; CliError naming those whose config did not come."""
    from u2sa_hw.config.param_file import LiveService, declared_for

    profile = profile_from(args)
    live: dict[str, LiveService] = {}
    silent: list[str] = []
    for d in answers:
        resp = bus.get_config(d.name, timeout=args.timeout)
        if resp is None:
            silent.append(d.name)
            continue
        fields = {f.name: (f.type_name, f.value) for f in resp.fields}
        kind = _kind_of(profile, d.name, d.service_type)
        live[d.name] = LiveService(d.name, kind, d.service_type, fields, declared_for(kind, fields))
    if silent:
        raise no_answer_error(args, f"{', '.join(silent)} answered discovery but not the config request within "
                              f"{args.timeout:g} s; nothing was done")
    return live


def _discover_all(args: Any, bus: Any, names: list[str]) -> tuple[list[Any], list[str]]:
    """Discovery answers of *names* (every service when empty) and every name heard; CliError when none answered."""
    from u2sa_hw.bus.client import unknown_service_text
    from u2sa_hw.cli import CliError

    heard = bus.discover(timeout=args.timeout)
    if not heard:
        raise no_answer_error(args, f"no service answered discovery within {args.timeout:g} s "
                              "(are services running, and on the same LCM URL and bus key?)")
    on_bus = [r.name for r in heard]
    for name in names:
        if name not in on_bus:
            raise CliError(unknown_service_text(name, on_bus))
    return [r for r in heard if not names or r.name in names], on_bus


def cmd_param_save(args: Any) -> int:
    """``u2sa param save FILE [SERVICE...]``: the services' config as a TOML parameter file."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.config.param_file import render

    with bus_client(args) as bus:
        answers, _ = _discover_all(args, bus, args.services)
        live = _live(args, bus, answers)
    profile = profile_from(args)
    if profile.path:
        vehicle = f"vehicle '{profile.name}' (system id {profile.system_id}, profile {profile.path})"
    else:
        vehicle = "no vehicle profile (system id 0)"
    now = datetime.now().astimezone().isoformat(timespec="seconds")
    which = "" if args.services else " on the bus"
    header = [f"u2sa parameters of {vehicle}",
              f"saved {now} by u2sa param save: {len(live)} service{'s' if len(live) != 1 else ''}{which}",
              "u2sa param load FILE --dry-run prints how the services differ from it; without --dry-run it applies it"]
    text = render(live.values(), header)
    if args.file == "-":
        sys.stdout.write(text)
        return 0
    path = Path(args.file)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent if str(path.parent) else ".")
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as fh:
                fh.write(text)
            os.replace(tmp, path)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise
    except OSError as exc:
        raise CliError(f"cannot write {path}: {exc.strerror or exc}") from None
    fields = sum(len(s.fields) for s in live.values())
    print(f"saved {fields} fields of {len(live)} service{'s' if len(live) != 1 else ''} "
          f"({', '.join(live)}) to {path}")
    return 0


def cmd_param_load(args: Any) -> int:
    """``u2sa param load FILE [SERVICE...] [--dry-run]``: print the differences, then apply them per service."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.config.param_file import plan_load

    path = Path(args.file)
    try:
        text = path.read_bytes().decode("utf-8")
    except OSError as exc:
        raise CliError(f"cannot read {path}: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise CliError(f"{path}: not a text file (byte {exc.start} is not UTF-8)") from None
    try:
        tables = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise CliError(f"{path}: not valid TOML ({exc}); nothing was changed") from None
    wanted = [n for n in (args.services or tables) if n in tables]
    with bus_client(args) as bus:
        heard = bus.discover(timeout=args.timeout)
        if not heard:
            raise no_answer_error(args, f"no service answered discovery within {args.timeout:g} s "
                                  "(are services running, and on the same LCM URL and bus key?)")
        live = _live(args, bus, [r for r in heard if r.name in wanted])
        plan = plan_load(str(path), text, [r.name for r in heard], live, only=args.services)
        if plan.problems:
            for problem in plan.problems:
                print(f"u2sa: {problem}", file=sys.stderr)
            raise CliError(f"{path}: {len(plan.problems)} problem{'s' if len(plan.problems) != 1 else ''}; "
                           "nothing was changed")
        for changes in plan.changes.values():
            for c in changes:
                print(f"{c.service}.{c.field}: {c.old_text} -> {c.new_text}")
        services = len(plan.changes)
        summary = (f"{path}: {plan.count} change{'s' if plan.count != 1 else ''} to {services} "
                   f"service{'s' if services != 1 else ''}, {plan.unchanged} field{'s' if plan.unchanged != 1 else ''} "
                   "already equal")
        if not plan.count:
            print(f"{path}: no differences ({plan.unchanged} field{'s' if plan.unchanged != 1 else ''} already "
                  "equal); nothing to change")
            return 0
        if args.dry_run:
            print(f"{summary}; --dry-run: nothing changed")
            return 0
        failed = [name for name, changes in plan.changes.items() if not _apply(args, bus, path, changes)]
    if failed:
        applied = [name for name in plan.changes if name not in failed]
        rest = f"; applied to {', '.join(applied)}" if applied else ""
        raise CliError(f"{path}: not loaded into {', '.join(failed)} (see above){rest}")
    print(f"{summary}; applied")
    return 0


def _apply(args: Any, bus: Any, path: Path, changes: list[Any]) -> bool:
    """Apply one service's *changes* in order; on a refusal, undo those applied (newest first). True when all held."""
    done: list[Any] = []
    for c in changes:
        resp = bus.set_config(c.service, c.field, c.new_text, timeout=args.timeout)
        if resp is not None and resp.ok:
            if resp.error:
                print(f"u2sa: warning: {c.service}: {resp.error}", file=sys.stderr)
            done.append(c)
            continue
        why = "refused: " + resp.error if resp is not None else f"did not answer within {args.timeout:g} s"
        print(f"u2sa: {path}:{c.line}: {c.service} {why}", file=sys.stderr)
        if resp is None:
            done.append(c)   # it may have been applied, its answer lost: set it back too
        stuck = []
        for u in reversed(done):
            back = bus.set_config(u.service, u.field, u.old_text, timeout=args.timeout)
            if back is None or not back.ok:
                stuck.append(f"{u.field} = {u.new_text}")
        if stuck:
            print(f"u2sa: {c.service}: rolling back failed, still set: {', '.join(stuck)} "
                  "(u2sa param list shows its values)", file=sys.stderr)
        else:
            print(f"u2sa: {c.service}: rolled back {len(done)} change{'s' if len(done) != 1 else ''}; "
                  "nothing of it changed", file=sys.stderr)
        return False
    return True
