"""The config fields every service has, before its kind's own (``U2SAService.CONFIG``).

A module of its own below :mod:`u2sa_hw.service.contract`: the settings checks
(:mod:`u2sa_hw.service.validate`, ``u2sa check``) read a kind's whole field list without importing
the service contract and its transport.
"""

from __future__ import annotations

from u2sa_hw.config.fields import ConfigField, field
from u2sa_hw.service.log import LEVEL_NAMES

BASE_CONFIG: tuple[ConfigField, ...] = (
    field("health_interval_s", 1.0, "seconds between health messages", gt=0, le=60),
    field("log_level", "", "debug, info, warn or error; empty: the vehicle profile's log_level",
          choices=("", *LEVEL_NAMES)),
)
