"""Hardware in the loop: replay of recorded device I/O against mock devices, and reports.

``hil.replay`` runs the real drivers against devices that play a log's ``RAW.<device>``
records back (``hil.replay_devices``, ``hil.replay_buses``), timed by ``hil.player``;
``hil.compare`` checks the replayed outputs against the recorded ones. ``u2sa replay`` is
the command line (u2sa_hw/cli/replay_cmd.py); docs/replay.md explains it.
"""
