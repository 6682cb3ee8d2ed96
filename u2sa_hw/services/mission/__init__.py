"""The Mission Manager service."""
