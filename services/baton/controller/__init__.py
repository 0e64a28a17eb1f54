"""The mission controller: Algorithm 1, the log ring, replay, and the drone-API proxy."""
