"""The safety chain: the software RC mux, command gating, pre-arm checks (see docs/safety.md)."""
