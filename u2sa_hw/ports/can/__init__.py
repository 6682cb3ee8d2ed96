"""The CAN port kind (docs/ports.md, "Port kinds"): ``can://INTERFACE/CHANNEL``, ``mock+can://``.

``grammar`` its addresses (the python-can bus options one may carry), ``kind`` its ``PortKind``,
``port`` the port over python-can (SocketCAN on a vehicle; ``udp_multicast``/``virtual`` as
mocks), ``clock`` the stamped udp_multicast bus a replay sends, ``probe`` its ``u2sa check
--probe``, ``install`` the interface's bitrate at boot.
"""
