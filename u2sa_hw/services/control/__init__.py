"""The Control System service: PID on heading and speed, mixed for the configured drive."""
