"""A compass on a serial port: NMEA heading/attitude sentences or the OS5000 format, bursts, calibration."""
