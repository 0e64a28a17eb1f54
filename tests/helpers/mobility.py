"""The drone service's side of a vehicle: MavsdkMobility connected to one, ready to fly."""

from __future__ import annotations

from waiting import eventually

from baton.drone.mobility import MavsdkMobility
from baton.v1 import drone_api_pb2 as api


async def connected_mobility(url: str) -> MavsdkMobility:
    """MavsdkMobility on the vehicle at ``url``, started and waited for until the
    vehicle is connected and ready to arm."""
    mobility = MavsdkMobility(url)
    await mobility.start()

    async def ready() -> bool:
        return (
            mobility.connected
            and (await mobility.GetFlightState(api.GetFlightStateRequest())).ready
        )

    await eventually(ready, "vehicle connected and ready")
    return mobility
