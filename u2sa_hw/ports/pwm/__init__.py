"""The PWM port kinds (docs/ports.md, "Port kinds"): ``pwm://pwmchipN/CHANNEL`` and ``pca9685://BUS/CHIP/CHANNEL``.

``grammar`` the sysfs addresses (a PCA9685's are I2C ones), ``kind`` its two ``PortKind`` classes,
``port`` the ``PwmChannel`` protocol and the sysfs backend (a sysfs-shaped directory as the
mock), ``pca9685`` the PCA9685 backend (real or on the mock I2C bus), ``probe`` the sysfs
``u2sa check --probe``, ``install`` the unit drop-in a sysfs chip needs.
"""
