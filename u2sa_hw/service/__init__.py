"""The service layer: the contract every U2SA service keeps, its bus handlers, health, log and systemd notification."""
