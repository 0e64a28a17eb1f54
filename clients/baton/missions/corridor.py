"""A corridor survey: photograph a line of waypoints (a pipeline, a road, a railway).

Fly ``length_m`` along ``bearing_deg`` (90: east) from the take-off point,
with a waypoint every ``spacing_m`` (the take-off point and the far end
included) at ``altitude_m`` and ``speed_m_s``, a picture at each, then land
where it ends (``survey.py`` flies it). Long enough to leave the range of the
station it started with: the mission the range-driven handover policy is for
(examples/corridor.yaml).

Run it with ``baton controller --mission examples/corridor_mission.py`` or
``baton testbed --config examples/corridor.yaml --mission corridor``.
"""

from __future__ import annotations

import math

from baton.missions.survey import survey
from baton.sdk import Drone


def waypoints(
    length_m: float, spacing_m: float, bearing_deg: float = 90.0
) -> list[tuple[float, float]]:
    """(north, east) offsets of the corridor's waypoints, from the take-off point out."""
    if not 0 < spacing_m <= length_m:
        raise ValueError(
            f"spacing_m must be > 0 and at most length_m ({length_m:g}), got {spacing_m:g}"
        )
    count = math.floor(length_m / spacing_m + 1e-9)
    north, east = math.cos(math.radians(bearing_deg)), math.sin(math.radians(bearing_deg))
    return [(k * spacing_m * north, k * spacing_m * east) for k in range(count + 1)]


def mission(
    drone: Drone,
    length_m: float = 1500.0,
    spacing_m: float = 100.0,
    bearing_deg: float = 90.0,
    altitude_m: float = 10.0,
    speed_m_s: float = 5.0,
    poll_s: float = 1.0,
    arrive_m: float = 1.0,
) -> None:
    """Flies the corridor and photographs every waypoint."""
    targets = waypoints(length_m, spacing_m, bearing_deg)
    survey(drone, targets, altitude_m, speed_m_s, poll_s, arrive_m)
