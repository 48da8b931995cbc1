"""A scenario played by the station (placeholder replaced below)."""
