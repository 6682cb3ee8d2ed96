"""``u2sa sim``: the whole stack on mock devices around one simulated vehicle, driving a mission.

``runner`` (SimRun: the steps), ``profile`` (the simulation copy of a vehicle profile),
``scenario`` (goals and obstacles), ``progress`` (the bus monitor and the progress line),
``summary`` and ``plot`` (what is written to ``--out``). See docs/simulation.md.
"""

# One module, one name: this folder installs as u2sa_hw.simulation (setup.py). Imported as a top-level
# 'simulation' (a script run from the source tree) it would load a second copy of every module.
if __name__ != "u2sa_hw.simulation":
    raise ImportError(f"import this package as u2sa_hw.simulation, not {__name__}: the simulation/ folder is "
                      "installed inside u2sa_hw (make venv, or pip install -e . in the source tree)")
