"""The paper's mission (Section 5.3): photograph a grid of waypoints.

Wait until the vehicle is ready to arm, take off to ``altitude_m``, visit a
``grid`` x ``grid`` grid of waypoints ``spacing_m`` apart (a serpentine,
starting above the take-off point) at ``speed_m_s``, polling the position
every ``poll_s`` seconds, take a picture at each waypoint, and land.

Where the grid is: it is laid out from the vehicle's position read just
before arming, on the ground. That is where ArduPilot and PX4 put home when
they arm, whereas a home read earlier can be elsewhere (ArduPilot's boot-time
home is wherever its first GPS fix was). The speed is set once airborne:
ArduCopter refuses a speed change before takeoff, and the drone service
re-applies it after every goto (ArduCopter resets it at each reposition).

Run it with ``baton controller --mission examples/grid_mission.py`` or as its
own process with ``python -m baton.sdk.run examples/grid_mission.py HOST:PORT
[grid=3 ...]``.
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


def wait_until_ready(drone: Drone, poll_s: float) -> None:
    """Polls until the vehicle can be armed, saying why not whenever the reason changes."""
    said = ""
    while not (state := drone.mobility.flight_state()).ready:
        if state.not_ready_reason != said:
            said = state.not_ready_reason
            print(f"waiting for the vehicle: {said}", flush=True)
        drone.clock.sleep(poll_s)


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
    wait_until_ready(drone, poll_s)
    origin = drone.mobility.position()
    drone.mobility.arm()
    drone.mobility.takeoff(altitude_m)
    while drone.mobility.position().relative_altitude_m < altitude_m - 0.5:
        drone.clock.sleep(poll_s)
    drone.mobility.set_speed(speed_m_s)
    targets = waypoints(grid, spacing_m)
    for k, (north, east) in enumerate(targets, start=1):
        target = offset(origin, north, east)
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
