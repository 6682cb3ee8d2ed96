"""Device drivers (the interaction layer): one module per device family, each a U2SA Sensor or Actuator service."""
