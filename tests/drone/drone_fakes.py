"""An in-process stand-in for the MAVSDK backend: enough state to see commands land."""

from __future__ import annotations

import asyncio

import grpc

from baton.drone.safety import VehicleLimits
from baton.rpc.errors import StatusError
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2

HOME = api.Position(
    latitude_deg=47.397742, longitude_deg=8.545594, absolute_altitude_m=488.0, relative_altitude_m=0
)


class FakeMobility:
    """Implements MobilityBackend; moves instantly and counts every call."""

    def __init__(self, url: str = "fake://vehicle", connected: bool = True) -> None:
        self.url = url
        self.is_connected = connected
        self.calls: list[str] = []
        self.armed = False
        self.position = api.Position()
        self.position.CopyFrom(HOME)
        # While set and not open, Goto waits for it after it started (the
        # autopilot's acknowledgement taking its time).
        self.gate: asyncio.Event | None = None
        # Ground velocity, m/s north and east (the handover policy reads it).
        self.velocity: tuple[float, float] | None = (0.0, 0.0)
        self.roi: api.Position | None = None
        # The cruise speed a restarted drone gave back from its state file.
        self.restored_speed: float | None = None
        # The bounds the fake autopilot says (None: not asked yet).
        self.limits: VehicleLimits | None = None

    @property
    def connected(self) -> bool:
        return self.is_connected

    def link(self) -> drone_pb2.VehicleLink:
        if self.is_connected:
            return drone_pb2.VehicleLink(healthy=True)
        return drone_pb2.VehicleLink(problem="fake vehicle disconnected")

    def ground_velocity(self) -> tuple[float, float] | None:
        return self.velocity if self.is_connected else None

    async def start(self) -> None:
        pass

    async def close(self) -> None:
        pass

    def _call(self, name: str) -> None:
        self.calls.append(name)

    async def Arm(self, request: api.ArmRequest) -> api.ArmReply:
        self._call("Arm")
        self.armed = True
        return api.ArmReply()

    async def Disarm(self, request: api.DisarmRequest) -> api.DisarmReply:
        self._call("Disarm")
        self.armed = False
        return api.DisarmReply()

    async def Takeoff(self, request: api.TakeoffRequest) -> api.TakeoffReply:
        self._call("Takeoff")
        if not self.armed:
            raise StatusError(grpc.StatusCode.ABORTED, "Takeoff: command denied (not armed)")
        self.position.relative_altitude_m = request.altitude_m
        return api.TakeoffReply()

    def looking_at(self) -> api.Position | None:
        return self.roi

    async def SetRoiLocation(self, request: api.SetRoiLocationRequest) -> api.SetRoiLocationReply:
        self._call("SetRoiLocation")
        self.roi = api.Position(
            latitude_deg=request.latitude_deg,
            longitude_deg=request.longitude_deg,
            relative_altitude_m=request.relative_altitude_m,
        )
        return api.SetRoiLocationReply()

    async def ClearRoi(self, request: api.ClearRoiRequest) -> api.ClearRoiReply:
        self._call("ClearRoi")
        self.roi = None
        return api.ClearRoiReply()

    async def Goto(self, request: api.GotoRequest) -> api.GotoReply:
        self._call("Goto")
        if self.gate is not None:
            await self.gate.wait()
        self.position.latitude_deg = request.latitude_deg
        self.position.longitude_deg = request.longitude_deg
        self.position.relative_altitude_m = request.relative_altitude_m
        return api.GotoReply()

    def autopilot_limits(self) -> VehicleLimits | None:
        return self.limits

    def restore_speed(self, speed_m_s: float) -> None:
        self.restored_speed = speed_m_s

    async def SetSpeed(self, request: api.SetSpeedRequest) -> api.SetSpeedReply:
        self._call("SetSpeed")
        return api.SetSpeedReply()

    async def Hold(self, request: api.HoldRequest) -> api.HoldReply:
        self._call("Hold")
        return api.HoldReply()

    async def Land(self, request: api.LandRequest) -> api.LandReply:
        self._call("Land")
        self.position.relative_altitude_m = 0
        return api.LandReply()

    async def ReturnToLaunch(self, request: api.ReturnToLaunchRequest) -> api.ReturnToLaunchReply:
        self._call("ReturnToLaunch")
        self.position.CopyFrom(HOME)
        return api.ReturnToLaunchReply()

    async def GetPosition(self, request: api.GetPositionRequest) -> api.GetPositionReply:
        self._call("GetPosition")
        return api.GetPositionReply(position=self.position)

    async def GetHome(self, request: api.GetHomeRequest) -> api.GetHomeReply:
        self._call("GetHome")
        return api.GetHomeReply(home=HOME)

    async def GetFlightState(self, request: api.GetFlightStateRequest) -> api.GetFlightStateReply:
        self._call("GetFlightState")
        return api.GetFlightStateReply(
            armed=self.armed,
            in_air=self.position.relative_altitude_m > 0,
            flight_mode="HOLD",
            battery_percent=100.0,
            ready=True,
            armable=True,
            landed_state="IN_AIR" if self.position.relative_altitude_m > 0 else "ON_GROUND",
        )
