"""Digital GPIO lines as services: outputs (an Actuator) and inputs such as an e-stop (a Sensor)."""
