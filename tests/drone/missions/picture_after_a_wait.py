"""Flies one leg, waits at its end, photographs the waypoint and lands.

Between the Goto and the picture the drone is sent nothing (the sleep is answered by
the controllers), so a drone killed after the Goto gets the picture as the first
request of its restarted service. The picture must be taken at the waypoint.
"""

from __future__ import annotations

from baton.missions.survey import wait_until_ready
from baton.sdk import Drone, distance_m, offset

NORTH_M = 20.0
ALTITUDE_M = 5.0
# Mission seconds: the vehicle arrives meanwhile (4 s at 5 m/s), and a test has this
# long (divided by the speed-up) to kill the drone before the picture is asked for.
WAIT_S = 200.0
# How far from the waypoint a picture may be taken (the grid mission's 2 * arrive_m).
PLACED_M = 2.0


def mission(drone: Drone) -> None:
    """Up, one leg north, a long wait there, the picture checked against the waypoint,
    down."""
    wait_until_ready(drone, 1.0)
    origin = drone.mobility.position()
    drone.mobility.arm()
    drone.mobility.takeoff(ALTITUDE_M)
    while drone.mobility.position().relative_altitude_m < ALTITUDE_M - 0.5:
        drone.clock.sleep(1.0)
    target = offset(origin, NORTH_M, 0.0)
    drone.mobility.goto(target, relative_altitude_m=ALTITUDE_M)
    drone.clock.sleep(WAIT_S)
    picture = drone.camera.take_picture()
    away = distance_m(picture.position, target)
    if away > PLACED_M:
        raise RuntimeError(f"picture {picture.sequence} taken {away:.0f} m away from the waypoint")
    print(f"picture {picture.sequence} at the waypoint ({away:.1f} m)", flush=True)
    drone.mobility.land()
    while drone.mobility.flight_state().in_air:
        drone.clock.sleep(1.0)
