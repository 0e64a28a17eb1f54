"""The paper's mission (Section 5.3): photograph a grid of waypoints.

Take off to ``altitude_m``, visit a ``grid`` x ``grid`` grid of waypoints
``spacing_m`` apart (a serpentine, starting above home) at ``speed_m_s``,
polling the position every ``poll_s`` seconds, take a picture at each
waypoint, and land. Run it with ``baton controller --mission
examples/grid_mission.py`` or as its own process with ``python -m
baton.sdk.run examples/grid_mission.py HOST:PORT [grid=3 ...]``.
"""

from __future__ import annotations

from baton.sdk import Drone, distance_m, offset


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
    while not drone.mobility.flight_state().ready:
        drone.clock.sleep(poll_s)
    home = drone.mobility.home()
    drone.mobility.set_speed(speed_m_s)
    drone.mobility.arm()
    drone.mobility.takeoff(altitude_m)
    while drone.mobility.position().relative_altitude_m < altitude_m - 0.5:
        drone.clock.sleep(poll_s)
    targets = waypoints(grid, spacing_m)
    for k, (north, east) in enumerate(targets, start=1):
        target = offset(home, north, east)
        drone.mobility.goto(target, relative_altitude_m=altitude_m)
        while distance_m(drone.mobility.position(), target) > arrive_m:
            drone.clock.sleep(poll_s)
        picture = drone.camera.take_picture()
        if distance_m(picture.position, target) > 2 * arrive_m:
            raise RuntimeError(f"picture {picture.sequence} taken away from waypoint {k}")
        print(
            f"waypoint {k} of {len(targets)}: picture {picture.sequence} "
            f"({len(picture.image)} bytes)",
            flush=True,
        )
    drone.mobility.land()
    while drone.mobility.flight_state().in_air:
        drone.clock.sleep(poll_s)
    print("mission complete", flush=True)
