"""The vehicle profile's types: what :func:`u2sa_hw.profile.loader.load_profile` makes of ``vehicle.toml``.

:class:`VehicleProfile` (the whole profile), :class:`ServiceSpec` (one ``[services.NAME]`` table),
:class:`Origin` (the local frame's origin) and :class:`ProfileError`. They import nothing of the
profile's parsers, so every parser (safety, geofence, supervision, config kinds) can name them while
the loader imports the parsers; the file format is documented in :mod:`u2sa_hw.profile.loader`.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


class ProfileError(ValueError):
    """The vehicle profile is missing or invalid; the message names the file, the key and the fix."""


@dataclass(frozen=True)
class ServiceSpec:
    """One service of the profile."""

    name: str
    kind: str
    config_path: Path
    settings: dict[str, Any] = field(default_factory=dict)
    enabled: bool = True
    required: bool = True

    def file_settings(self) -> dict[str, Any]:
        """The service's config file as a table, leniently: empty when it is missing, unreadable or not TOML
        (``u2sa check`` and the old-form scan judge what they can; the service itself refuses such a file)."""
        try:
            read = tomllib.loads(self.config_path.read_bytes().decode("utf-8"))
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
            return {}
        return read if isinstance(read, dict) else {}


@dataclass(frozen=True)
class Origin:
    """The local frame's origin (degrees, metres)."""

    lat: float = 0.0
    lon: float = 0.0
    alt: float = 0.0


@dataclass(frozen=True)
class VehicleProfile:
    """A parsed vehicle profile."""

    path: Path | None
    name: str = "vehicle"
    system_id: int = 1
    lcm_url: str | None = None
    bus_security: str | None = None     # None: $U2SA_BUS_SECURITY, else signed
    bus_key: Path | None = None         # None: $U2SA_BUS_KEY_FILE, else /etc/u2sa/bus.key
    bus_interface: str | None = None    # ttl >= 1: join and send only there (None: the default route's)
    config_dir: Path = Path(".u2sa/config")
    log_dir: Path = Path(".u2sa/logs")
    data_dir: Path = Path(".u2sa/data")
    log_level: str = "info"
    origin: Origin = Origin()
    services: dict[str, ServiceSpec] = field(default_factory=dict)
    devices: dict[str, dict[str, Any]] = field(default_factory=dict)
    raw: dict[str, Any] = field(default_factory=dict)

    def service(self, name: str) -> ServiceSpec:
        """The service called *name*; ProfileError lists the profile's services."""
        try:
            return self.services[name]
        except KeyError:
            where = self.path or "the default profile"
            known = ", ".join(self.services) or "none"
            raise ProfileError(f"{where}: no service '{name}' (services: {known})") from None

    def resolve_path(self, text: str) -> Path | None:
        """A file named in a config (``~`` expanded), relative to the profile's directory; None if empty."""
        text = text.strip()
        if not text:
            return None
        path = Path(text).expanduser()
        if not path.is_absolute():
            path = (self.path.resolve().parent if self.path else Path.cwd()) / path
        return path

    def config_path_for(self, name: str) -> Path:
        """Where the config file of service *name* lives."""
        spec = self.services.get(name)
        return spec.config_path if spec else self.config_dir / f"{name}.toml"
