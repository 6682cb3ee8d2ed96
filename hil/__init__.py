"""Hardware in the loop: replay of recorded device I/O against mock devices, and reports.

``u2sa_hw.hil.replay`` runs the real drivers against devices that play a log's ``RAW.<device>``
records back (``u2sa_hw.hil.replay_devices``, ``u2sa_hw.hil.replay_buses``), timed by ``u2sa_hw.hil.player``;
``u2sa_hw.hil.compare`` checks the replayed outputs against the recorded ones. ``u2sa replay`` is
the command line (u2sa_hw/cli/replay_cmd.py); docs/replay.md explains it.
"""

# One module, one name: this folder installs as u2sa_hw.hil (setup.py). Imported as a top-level
# 'hil' (a script run from the source tree) it would load a second copy of every module.
if __name__ != "u2sa_hw.hil":
    raise ImportError(f"import this package as u2sa_hw.hil, not {__name__}: the hil/ folder is "
                      "installed inside u2sa_hw (make venv, or pip install -e . in the source tree)")
