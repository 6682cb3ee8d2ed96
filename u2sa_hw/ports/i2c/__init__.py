"""The I2C port kind (docs/ports.md, "Port kinds"): ``i2c://BUS/CHIP``, ``mock+i2c:///BUS.sock/CHIP``.

``grammar`` its addresses (and the bus part of a PCA9685's), ``kind`` its ``PortKind``, ``port``
the port (smbus2 on a vehicle, the mock bus client), ``wire`` the mock bus's protocol whose other
end the mock devices serve, ``probe`` its ``u2sa check --probe`` (a chip's identity).
"""
