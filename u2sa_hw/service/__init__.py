"""The service layer: the contract every U2SA service keeps, its base config and its settings checked
against its kind, its bus handlers, health, log and systemd notification."""
