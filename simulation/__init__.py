"""``u2sa sim``: the whole stack on mock devices around one simulated vehicle, driving a mission.

``runner`` (SimRun: the steps), ``profile`` (the simulation copy of a vehicle profile),
``scenario`` (goals and obstacles), ``progress`` (the bus monitor and the progress line),
``summary`` and ``plot`` (what is written to ``--out``). See docs/simulation.md.
"""
