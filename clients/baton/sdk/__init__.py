"""The mission SDK: write a drone mission as a plain Python function.

    from baton.sdk import connect

    with connect("127.0.0.1:7100") as drone:
        drone.mobility.arm()
        drone.mobility.takeoff(10)
        while drone.mobility.position().relative_altitude_m < 9.5:
            drone.clock.sleep(1)

The program talks to its local controller, which proxies the calls to the
drone (or answers them from the log); it never knows which. Calls are made
one at a time; a failed call raises ``DroneCallError`` naming the RPC and its
status. ``baton.sdk.aio`` is the same API for asyncio (``async def mission``).
"""

from baton.sdk.drone import Drone, connect
from baton.sdk.errors import ConcurrentCallError, DroneCallError
from baton.sdk.geo import distance_m, offset
from baton.sdk.types import FlightState, Picture, Position

__all__ = [
    "ConcurrentCallError",
    "Drone",
    "DroneCallError",
    "FlightState",
    "Picture",
    "Position",
    "connect",
    "distance_m",
    "offset",
]
