"""What the drone service needs from a vehicle backend (MAVSDK in practice).

The drone service dispatches ``/baton.v1.Mobility/*`` and ``/baton.v1.Gimbal/*``
calls to an object with one coroutine per RPC of those services, named as in the proto, taking
the request message and returning the reply message. A failure is raised as
``baton.rpc.errors.StatusError`` with the right status code and, for
autopilot refusals, MAVSDK's own reason in the message.
"""

from __future__ import annotations

import asyncio
from typing import Protocol

from baton.drone.safety import VehicleLimits
from baton.rpc.errors import StatusError
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2


class MobilityBackend(Protocol):
    """One coroutine per Mobility RPC, plus connection management."""

    url: str

    async def start(self) -> None:
        """Starts connecting to the vehicle; returns without waiting for it."""

    async def close(self) -> None:
        """Releases the connection."""

    @property
    def connected(self) -> bool:
        """Whether the autopilot is there now (heartbeats arriving, telemetry fresh)."""

    def link(self) -> drone_pb2.VehicleLink:
        """The link to the autopilot now: ages, the problem if any, outages."""

    def ground_velocity(self) -> tuple[float, float] | None:
        """The vehicle's ground velocity now, metres per second north and east, from the
        telemetry cache; None while it is not known (the handover policy's input)."""

    def looking_at(self) -> api.Position | None:
        """The region of interest the gimbal points at (Gimbal.SetRoiLocation accepted
        last, not cleared since); None if none is set. The camera records it."""

    def autopilot_limits(self) -> VehicleLimits | None:
        """The bounds the autopilot said at its last connect (``safety.vehicle_limits``);
        None until it was asked."""

    def restore_speed(self, speed_m_s: float) -> None:
        """The cruise speed the mission set before the drone restarted (its durable
        state): sent again with the next goto, as a SetSpeed's would be."""

    async def Arm(self, request: api.ArmRequest) -> api.ArmReply: ...
    async def Disarm(self, request: api.DisarmRequest) -> api.DisarmReply: ...
    async def Takeoff(self, request: api.TakeoffRequest) -> api.TakeoffReply: ...
    async def Goto(self, request: api.GotoRequest) -> api.GotoReply: ...
    async def SetSpeed(self, request: api.SetSpeedRequest) -> api.SetSpeedReply: ...
    async def Hold(self, request: api.HoldRequest) -> api.HoldReply: ...
    async def Land(self, request: api.LandRequest) -> api.LandReply: ...
    async def ReturnToLaunch(
        self, request: api.ReturnToLaunchRequest
    ) -> api.ReturnToLaunchReply: ...
    async def GetPosition(self, request: api.GetPositionRequest) -> api.GetPositionReply: ...
    async def GetHome(self, request: api.GetHomeRequest) -> api.GetHomeReply: ...
    async def GetFlightState(
        self, request: api.GetFlightStateRequest
    ) -> api.GetFlightStateReply: ...

    # The Gimbal service (reached over the same link; drone/dispatch.py ANSWERED_BY).
    async def SetRoiLocation(
        self, request: api.SetRoiLocationRequest
    ) -> api.SetRoiLocationReply: ...
    async def ClearRoi(self, request: api.ClearRoiRequest) -> api.ClearRoiReply: ...


async def command_action(vehicle: MobilityBackend, action: str) -> bool:
    """Commands ``vehicle`` what a failsafe or an operator's command says: ``hold``,
    ``land`` or ``rtl`` (StatusError if it refuses); False for any other action, which
    the caller carries out itself."""
    if action == "hold":
        await vehicle.Hold(api.HoldRequest())
    elif action == "land":
        await vehicle.Land(api.LandRequest())
    elif action == "rtl":
        await vehicle.ReturnToLaunch(api.ReturnToLaunchRequest())
    else:
        return False
    return True


# A read of the vehicle must not hang on a vehicle that stopped answering.
READ_TIMEOUT_S = 1.0


async def latest_position(vehicle: MobilityBackend) -> api.Position:
    """The vehicle's position, or an all-zero Position if it is not known now."""
    if not vehicle.connected:
        return api.Position()
    try:
        reply = await asyncio.wait_for(
            vehicle.GetPosition(api.GetPositionRequest()), READ_TIMEOUT_S
        )
    except (StatusError, TimeoutError):
        return api.Position()
    return reply.position
