"""Vendor register and command tables shared by drivers and mock devices, one module per vendor."""
