"""VESC motor controllers over CAN (VESC mode, extended ids)."""
