"""sensorbox package."""
