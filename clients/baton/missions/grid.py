"""The paper's mission (Section 5.3): photograph a grid of waypoints.

Visit a ``grid`` x ``grid`` grid of waypoints ``spacing_m`` apart (a
serpentine, starting above the take-off point) at ``altitude_m`` and
``speed_m_s``, polling the position every ``poll_s`` seconds, take a picture
at each waypoint, and land (``survey.py`` flies it).

Run it with ``baton controller --mission examples/grid_mission.py`` or as its
own process with ``python -m baton.sdk.run examples/grid_mission.py HOST:PORT
[grid=3 ...]``.
"""

from __future__ import annotations

from baton.missions.survey import survey, wait_until_ready
from baton.sdk import Drone

__all__ = ["mission", "wait_until_ready", "waypoints"]


def waypoints(grid: int, spacing_m: float) -> list[tuple[float, float]]:
    """(north, east) offsets of the grid, row by row, alternating direction."""
    points: list[tuple[float, float]] = []
    for row in range(grid):
        cols = range(grid) if row % 2 == 0 else reversed(range(grid))
        points.extend((row * spacing_m, col * spacing_m) for col in cols)
    return points


def mission(
    drone: Drone,
    grid: int = 5,
    spacing_m: float = 50.0,
    altitude_m: float = 10.0,
    speed_m_s: float = 5.0,
    poll_s: float = 1.0,
    arrive_m: float = 1.0,
) -> None:
    """Flies the grid and photographs every waypoint."""
    survey(drone, waypoints(grid, spacing_m), altitude_m, speed_m_s, poll_s, arrive_m)
