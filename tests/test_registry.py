"""The service registry's tables against the classes they name."""

from __future__ import annotations

import subprocess
import sys

import pytest

from u2sa_hw.abstract import Actuator
from u2sa_hw.registry import NOT_ACTUATOR_KINDS, SERVICE_KINDS, resolve_kind
from u2sa_hw.safety.wiring import RC_KIND


@pytest.mark.parametrize("kind", sorted(SERVICE_KINDS))
def test_not_actuator_table_matches_the_classes(kind: str) -> None:
    """A kind is in NOT_ACTUATOR_KINDS exactly when its class is neither an Actuator nor the RC mux."""
    cls = resolve_kind(kind)
    is_wired = issubclass(cls, Actuator) or kind == RC_KIND
    assert (kind in NOT_ACTUATOR_KINDS) == (not is_wired), kind


def test_a_service_process_imports_only_its_own_command_and_kind() -> None:
    """`u2sa service` registers only its own subcommand, and the RC mux's wiring skips non-actuators.

    Each service is its own process on a small board: numpy (calibration, the estimator),
    mcap (recording), pyserial and psutil must not load in a service that does not use them.
    """
    code = (
        "import sys\n"
        "from u2sa_hw.cli import build_parser, LEAN_COMMANDS\n"
        "build_parser(only=LEAN_COMMANDS['service'])\n"
        "from u2sa_hw.registry import resolve_kind\n"
        "resolve_kind('mission_manager'); resolve_kind('compass_serial'); resolve_kind('imu_mpu9250')\n"
        "from u2sa_hw.safety.wiring import profile_wiring\n"
        "from u2sa_hw.profile.loader import load_profile\n"
        "profile_wiring(load_profile('examples/ground_vehicle/vehicle.toml'))\n"
        "print(' '.join(m for m in ('numpy', 'mcap', 'psutil', 'tempfile', 'difflib') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    assert out.stdout.strip() == ""
