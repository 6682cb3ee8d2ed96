"""GPS over serial NMEA 0183: the driver, the epoch rules, what each sentence says, and the fix."""
