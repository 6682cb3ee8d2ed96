"""Servos and ESCs on PWM outputs (sysfs PWM or a PCA9685)."""
