"""Foxglove: the live WebSocket bridge of the bus and the mapping the log export shares (docs/foxglove.md)."""
