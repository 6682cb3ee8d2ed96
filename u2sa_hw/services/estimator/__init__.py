"""The State Estimator service."""
