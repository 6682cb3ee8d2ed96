"""The serial port kind (docs/ports.md, "Port kinds"): ``serial://``, ``serial+X://``, ``mock+serial://``.

``grammar`` its addresses (and the one framing table), ``kind`` its ``PortKind``, ``port`` the
port (pyserial; on a vehicle and on a mock device's pty alike), ``opener`` ``open_serial``,
``clock`` the stamped frames a replay's pty sends and the port that reads them, ``probe`` its
``u2sa check --probe``, ``install`` the udev rule that names a USB adapter.
"""
