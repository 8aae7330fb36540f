"""Light calibration: LED bar positions from their reflections in mirror spheres."""
