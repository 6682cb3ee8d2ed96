"""The Path Planner service: a state machine per goal type with obstacle avoidance."""
