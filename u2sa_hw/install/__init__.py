"""Deployment of a vehicle profile under systemd: ``u2sa install``, ``u2sa uninstall``, ``u2sa status``.

- :mod:`.deploy`: install and uninstall, step by step.
- :mod:`.files`: the installed tree, written idempotently; :mod:`.manifest`: its record.
- :mod:`.units`: what goes where (units, drop-ins, profile, configs, sysusers, tmpfiles, sysctl).
- :mod:`.system`: users and groups, the venv, systemd and udev reloads.
- :mod:`.status`: each unit's state next to the HSM's view.

Kept free of imports so that :mod:`.units` can be read (the launcher's watchdog does) without
loading the whole installer.
"""
