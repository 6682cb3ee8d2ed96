"""The World Modeler service."""
