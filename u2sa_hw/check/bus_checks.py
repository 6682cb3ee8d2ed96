"""``u2sa check`` on where the bus listens (docs/security.md, "Where the vehicle listens"), and on
``$U2SA_BUS_SECURITY`` in the environment.

Three warnings, never errors (the bus still verifies every message with the key):

* ``ttl=0`` while ``lo`` has no MULTICAST flag on this machine and the check does not run as
  root: the services cannot keep the bus on ``lo``. Those signed with the vehicle's key refuse
  to start; those with a key of their own run (``u2sa sim``) listen on the default route's
  interface too and say so in their health.
* ``ttl`` >= 1 without ``bus_interface``: the bus joins and sends on the default route's
  interface, which may be the WiFi, where every host that has the key can command the vehicle.
* ``$U2SA_BUS_SECURITY`` set where the check runs: the installed units (``u2sa service --unit``)
  ignore it, the profile's ``[vehicle] bus_security`` alone decides there; ``u2sa run``, the
  benches and the tests still honour it when the profile does not say. Whoever set it (a shell
  profile, a bench script) should know the vehicle will not do what it asks.
"""

from __future__ import annotations

import os
from typing import Any

from u2sa_hw.bus.listen import IFF_MULTICAST, interface_flags, is_local, route_interface
from u2sa_hw.check.problem import Collector
from u2sa_hw.bus.lcm_url import DEFAULT_LCM_URL


def check_bus(vehicle: dict[str, Any], out: Collector) -> None:
    """Warn when the profile's bus would be heard beyond where the vehicle lives (see the module docstring)."""
    url = vehicle.get("lcm_url")
    if not isinstance(url, str) or not url:
        url = DEFAULT_LCM_URL
    if not url.startswith("udpm://"):
        return
    if is_local(url):
        flags = interface_flags("lo")
        if flags is not None and not flags & IFF_MULTICAST and os.geteuid() != 0:
            out.warning("vehicle.lcm_url",
                        f"ttl=0, but lo has no MULTICAST flag on this machine: services not run as root cannot keep "
                        f"the bus on lo (signed with the vehicle's key they refuse to start; with a run's own key, "
                        f"as in u2sa sim, they also listen on {route_interface(url)} and say so in their health)",
                        "sudo ip link set lo multicast on (u2sa run as root sets it; on an installed vehicle the "
                        "u2sa-multicast-lo unit does)")
        return
    interface = vehicle.get("bus_interface")
    if not isinstance(interface, str) or not interface:
        out.warning("vehicle.bus_interface",
                    f"lcm_url has ttl >= 1 but no bus_interface: the bus joins and sends on the default route's "
                    f"interface (here {route_interface(url)}), which may be the WiFi; every host there that has "
                    "the key can command this vehicle",
                    "name the vehicle's own network in [vehicle], e.g. bus_interface = \"eth0\"")


def check_security_env(vehicle: dict[str, Any], out: Collector) -> None:
    """Warn when ``$U2SA_BUS_SECURITY`` is set here: the installed units ignore it (see the module docstring)."""
    from u2sa_hw.bus.auth import SECURITY_ENV

    value = os.environ.get(SECURITY_ENV)
    if value is None:
        return
    said = vehicle.get("bus_security")
    if isinstance(said, str) and said:
        decides = f'follow the profile\'s bus_security = "{said}" (which wins over the variable for u2sa run too)'
    else:
        decides = ("follow the profile, which has no bus_security in [vehicle]: they sign and verify every message. "
                   f"u2sa run, the benches and the tests still honour ${SECURITY_ENV} when the profile does not say")
    out.warning("vehicle.bus_security",
                f"${SECURITY_ENV}={value!r} is set in this environment, but the installed units (u2sa service "
                f"--unit) ignore it and {decides}",
                f"say what the vehicle does with bus_security in [vehicle], and unset {SECURITY_ENV} unless a bench "
                "or a test needs it")
