"""The drone service: the master's drone-API calls, each executed once."""
