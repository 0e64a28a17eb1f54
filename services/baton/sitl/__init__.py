"""ArduPilot SITL, started and stopped the way baton starts its own parts (``baton sitl``)."""
