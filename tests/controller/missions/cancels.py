"""A mission (asyncio API) that gives up on a TakePicture by cancelling it, then takes it again.

The SDK sends its calls on one stream it keeps to the controller; cancelling a
call cancels that stream, so the master sees the call given up (CANCELLED) as
it sees a unary call's, and logs it so. The drone link's latency makes the
program give up while the drone is at it: the drone takes that picture and
records it; the second TakePicture is a new request, on a new stream.
"""

import asyncio

from baton.sdk import DroneCallError
from baton.sdk.aio import Drone


async def mission(drone: Drone, wait_s: float = 0.45) -> None:
    await drone.mobility.position()
    try:
        await asyncio.wait_for(drone.camera.take_picture(), float(wait_s))
        print("first picture: reply", flush=True)
    except TimeoutError:
        print("first picture: gave up", flush=True)
    except DroneCallError as exc:  # a replica: the master's give-up, from the log
        print(f"first picture: {exc.code.name}", flush=True)
    await drone.camera.take_picture()
    await drone.mobility.position()
