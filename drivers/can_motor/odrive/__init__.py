"""ODrive motor controllers over CAN (CANSimple): the driver, its axis record, latched errors and watchdog set-up."""
