"""RC input and the hardware RC multiplexer: pulse measurement, the mode, the autonomy-enable line, the pilot's sticks."""
