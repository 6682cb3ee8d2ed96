"""``u2sa param list|get|set``: a service's configuration over the bus (requirement C7)."""

from __future__ import annotations

import argparse
import json
import re
import sys
import tomllib
from typing import Any

from u2sa_hw.cli.common import add_timeout_option, add_vehicle_option, bus_client, no_answer_error


_NEGATIVE_LITERAL = re.compile(r"^-(?:\d[\d_]*(?:\.\d[\d_]*)?(?:[eE][+-]?\d+)?|\.\d+|inf|nan)$")


def register(sub: Any) -> None:
    """Add the ``param`` subcommand group."""
    p = sub.add_parser("param", help="list, get or set a service's config over the bus",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Read and change a running service's typed config. A change is checked "
                       "against the field's type, allowed values and range by the service (a value out of range, or "
                       "inf/nan where the field needs a finite number, is refused with the bound and the value) "
                       "and written to its TOML file atomically; a refused change leaves the file untouched. "
                       "VALUE is a TOML literal: 42, 2.5, -5, true, \"text\". For a text field "
                       "a quoted string gives its contents and anything else is taken as it is, so "
                       "mode passthrough and mode '\"passthrough\"' both set passthrough.",
                       epilog="examples:\n  u2sa param list state_estimator --json\n"
                       "  u2sa param set gps baudrate 38400\n  u2sa param set state_estimator mode passthrough\n"
                       "  u2sa param set state_estimator log_level debug\n"
                       "  u2sa param set compass declination_deg -6.5   (a negative value needs no quoting)\n"
                       "  u2sa param set state_estimator log_level '\"\"'     (empty: the profile's level)")
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


def _value(field: Any) -> Any:
    try:
        return tomllib.loads(f"v = {field.value}")["v"]
    except tomllib.TOMLDecodeError:
        return field.value


def cmd_param(args: Any) -> int:
    """Dispatch ``param list/get/set``."""
    from u2sa_hw.cli import CliError

    with bus_client(args) as bus:
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
