"""A survey along a line east of home, to the eastings given (metres), in order."""

from __future__ import annotations

from baton.missions.survey import survey
from baton.sdk import Drone


def mission(
    drone: Drone,
    eastings: str = "0,100",
    altitude_m: float = 10.0,
    speed_m_s: float = 5.0,
    poll_s: float = 1.0,
    arrive_m: float = 1.0,
) -> None:
    """Photographs each easting on the way."""
    targets = [(0.0, float(east)) for east in eastings.split(",")]
    survey(drone, targets, altitude_m, speed_m_s, poll_s, arrive_m)
