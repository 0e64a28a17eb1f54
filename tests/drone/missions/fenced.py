"""Flies in the L-shaped fence of tests/drone/test_fence_end_to_end.py (home at the
corner, one arm NORTH_M north, one EAST_M east): up the north arm; a Goto out of the
fence, refused OUT_OF_RANGE (the mission goes on); then to the end of the east arm,
a target inside whose straight leg cuts the L's inner corner, out of the fence: the
drone's breach failsafe takes the vehicle, and the program's next call fails with it
(the mission ends with that error on every controller)."""

from __future__ import annotations

import grpc

from baton.sdk import Drone, DroneCallError, Position
from baton.sdk.geo import distance_m, offset

NORTH_M = EAST_M = 200.0
OUT_M = 400.0  # north of home: beyond the north arm's end
ALTITUDE_M = 10.0
ARRIVED_M = 3.0


def fly_to(drone: Drone, target: Position, poll_s: float) -> None:
    drone.mobility.goto(target, ALTITUDE_M)
    while distance_m(drone.mobility.position(), target) > ARRIVED_M:
        drone.clock.sleep(poll_s)


def mission(drone: Drone, poll_s: float = 0.5) -> None:
    """The north arm, a refused Goto, the east arm (cut short by the breach)."""
    home = drone.mobility.home()
    drone.mobility.set_speed(10.0)
    drone.mobility.arm()
    drone.mobility.takeoff(ALTITUDE_M)
    while drone.mobility.position().relative_altitude_m < ALTITUDE_M - 1.0:
        drone.clock.sleep(poll_s)
    fly_to(drone, offset(home, NORTH_M, 0.0), poll_s)
    try:
        drone.mobility.goto(offset(home, OUT_M, 0.0), ALTITUDE_M)
    except DroneCallError as err:
        assert err.code is grpc.StatusCode.OUT_OF_RANGE, err
        print(f"refused: {err}", flush=True)
    else:
        raise AssertionError("a Goto out of the fence was accepted")
    fly_to(drone, offset(home, 0.0, EAST_M), poll_s)
    raise AssertionError("the vehicle crossed the L's inner corner without a breach")
