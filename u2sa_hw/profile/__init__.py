"""The vehicle profile: vehicle.toml, its devices, and every number it holds outside a service's settings."""
