"""The GPIO port kind (docs/ports.md, "Port kinds"): ``gpio://CHIP/LINES``, ``mock+gpio:///CHIP.sock/LINES``.

``grammar`` its addresses, ``kind`` its ``PortKind``, ``port`` the port every backend hands
out, ``gpiod_backend`` the kernel's (libgpiod v2), ``mock_client`` the mock chip's client,
``wire`` the mock chip's protocol and the event types, ``probe`` its ``u2sa check --probe``.
"""
