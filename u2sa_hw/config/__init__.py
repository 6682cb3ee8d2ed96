"""Configuration: a service's typed config fields, unknown-key checks, validation, parameter files."""
