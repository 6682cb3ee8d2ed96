"""The recorder service: every LCM channel into rotated, crash-safe MCAP logs."""
