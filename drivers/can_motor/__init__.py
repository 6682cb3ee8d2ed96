"""CAN motor controllers: what the families share (bus, names, command timing, odometry, watchdogs), with one folder per family."""
