"""Configuration: typed config fields and the configurator, unknown-key checks, parameter files."""
