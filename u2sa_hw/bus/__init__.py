"""The bus layer: LCM transport, channels' UDP ports, signing (keys, keyring, pilot trailers, roles), filters and listeners."""
