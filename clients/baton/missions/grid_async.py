"""The paper's grid mission (``grid.py``) written with the asyncio SDK (``baton.sdk.aio``).

The same waypoints (``grid.waypoints``), the same calls in the same order as
``survey.py`` makes them, each awaited: wait until the vehicle is ready, take
off, fly the serpentine photographing every waypoint, land. Run it as any
mission file (``baton testbed --mission clients/baton/missions/grid_async.py
--mission-arg grid=3``, ``baton controller --mission ...``): ``baton.sdk.run``
sees the ``async def`` and gives it the asyncio ``Drone``.
"""

from __future__ import annotations

from baton.missions.grid import waypoints
from baton.sdk import distance_m, offset
from baton.sdk.aio import Drone

__all__ = ["mission"]


async def wait_until_ready(drone: Drone, poll_s: float) -> None:
    """Polls until the vehicle can be armed, saying why not whenever the reason changes."""
    said = ""
    while not (state := await drone.mobility.flight_state()).ready:
        if state.not_ready_reason != said:
            said = state.not_ready_reason
            print(f"waiting for the vehicle: {said}", flush=True)
        await drone.clock.sleep(poll_s)


async def mission(
    drone: Drone,
    grid: int = 5,
    spacing_m: float = 50.0,
    altitude_m: float = 10.0,
    speed_m_s: float = 5.0,
    poll_s: float = 1.0,
    arrive_m: float = 1.0,
) -> None:
    """Flies the grid and photographs every waypoint (see ``survey.py`` for why this order)."""
    targets = waypoints(grid, spacing_m)
    await wait_until_ready(drone, poll_s)
    origin = await drone.mobility.position()
    await drone.mobility.arm()
    await drone.mobility.takeoff(altitude_m)
    while (await drone.mobility.position()).relative_altitude_m < altitude_m - 0.5:
        await drone.clock.sleep(poll_s)
    await drone.mobility.set_speed(speed_m_s)
    for k, (north, east) in enumerate(targets, start=1):
        target = offset(origin, north, east)
        await drone.mobility.goto(target, relative_altitude_m=altitude_m)
        while distance_m(await drone.mobility.position(), target) > arrive_m:
            await drone.clock.sleep(poll_s)
        picture = await drone.camera.take_picture()
        if distance_m(picture.position, target) > 2 * arrive_m:
            raise RuntimeError(f"picture {picture.sequence} taken away from waypoint {k}")
        print(
            f"waypoint {k} of {len(targets)}: picture {picture.sequence} "
            f"({len(picture.image)} bytes)",
            flush=True,
        )
    await drone.mobility.land()
    while (await drone.mobility.flight_state()).in_air:
        await drone.clock.sleep(poll_s)
    print("mission complete", flush=True)
