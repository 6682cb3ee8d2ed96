"""Core services of the U2SA core layer (estimator, mission, world, planner, control, HSM, recorder)."""
