"""MAVSDK's Geofence plugin (through MavsdkMobility) against the sim vehicle: the fence
uploaded at connect, held by the vehicle, uploaded again by a restarted drone; an Arm
refused, the vehicle never armed, when the vehicle does not take the fence (issue 32,
item 3)."""

from __future__ import annotations

import math
from pathlib import Path

import grpc
import pytest
from waiting import eventually

from baton.drone.mobility import MavsdkMobility
from baton.effects import EffectsFile, read_effects
from baton.rpc.errors import StatusError
from baton.sdk import Position, offset
from baton.sdk.fence import Fence, FenceCircle, FencePolygon
from baton.sim_vehicle.fence_upload import MAX_ITEMS
from baton.sim_vehicle.kinematics import GeoPoint
from baton.sim_vehicle.server import SimVehicle
from baton.v1 import drone_api_pb2 as api

HOME = Position(47.397742, 8.545594, 488.0)


def polygon(corners: list[tuple[float, float]], inclusion: bool = True) -> FencePolygon:
    """The polygon of (north, east) metres from home, as MAVLink carries its vertices
    (degrees times 1e7, whole)."""
    points = [offset(HOME, n, e) for n, e in corners]
    return FencePolygon(
        tuple((round(p.latitude_deg, 7), round(p.longitude_deg, 7)) for p in points), inclusion
    )


def square(half_m: float, inclusion: bool = True) -> FencePolygon:
    h = half_m
    return polygon([(-h, -h), (-h, h), (h, h), (h, -h)], inclusion)


def uploads(effects: Path) -> int:
    """Fence uploads the vehicle accepted, as its effects file counts them."""
    return sum(e["effect"] == "fence" for e in read_effects(effects))


def sim_vehicle(effects: Path) -> SimVehicle:
    home = GeoPoint(HOME.latitude_deg, HOME.longitude_deg, HOME.absolute_altitude_m)
    vehicle = SimVehicle(home, speedup=10, effects=EffectsFile(effects))
    vehicle.start()
    return vehicle


async def test_the_fence_is_uploaded_at_connect_and_again_by_a_restarted_drone(
    tmp_path: Path,
) -> None:
    fence = Fence(
        (square(200.0), square(20.0, inclusion=False)),
        (FenceCircle(HOME.latitude_deg, HOME.longitude_deg, 300.0),),
        ceiling_m=60.0,
    )
    effects = tmp_path / "effects.jsonl"
    vehicle = sim_vehicle(effects)
    try:
        for drone in (1, 2):  # the second: the drone service restarted
            mobility = MavsdkMobility(vehicle.url, fence=fence)
            await mobility.start()
            try:
                await eventually(
                    lambda n=drone: uploads(effects) == n,
                    f"the fence uploaded by drone {drone} at connect",
                    20,
                )
                held = vehicle.state().fence
                assert held is not None
                assert (held.polygons, held.circles) == (fence.polygons, fence.circles)
            finally:
                await mobility.close()
    finally:
        vehicle.stop()


class LateLook(MavsdkMobility):
    """Its link watch looks first once position and SYS_STATUS flow already: the order a
    restarted drone service meets when the autopilot still streams at the rates the one
    before asked for (an autopilot sends what one asked to all)."""

    async def _watch(self) -> None:
        await eventually(
            lambda: self.monitor.position_at is not None and self.monitor.status_at is not None,
            "the streams flowing before the first look",
            20,
        )
        await super()._watch()


async def test_a_drone_restarted_while_the_streams_flow_still_uploads_its_fence(
    tmp_path: Path,
) -> None:
    """The connect-time set-up (fence, GCS failsafe, bounds) is due at each contact, not
    only when the streams must be asked for: a restarted drone whose autopilot streams
    already uploads the fence all the same."""
    fence = Fence((square(200.0),), ceiling_m=60.0)
    effects = tmp_path / "effects.jsonl"
    vehicle = sim_vehicle(effects)
    try:
        first = MavsdkMobility(vehicle.url, fence=fence)
        await first.start()
        try:
            await eventually(lambda: uploads(effects) == 1, "the first drone's fence", 20)
            restarted = LateLook(vehicle.url, fence=fence)
            await restarted.start()
            try:
                await eventually(lambda: uploads(effects) == 2, "the restarted drone's fence", 20)
                assert restarted.monitor.stream_requests == 0  # the streams were never asked
                assert restarted.autopilot_limits() is not None
            finally:
                await restarted.close()
        finally:
            await first.close()
    finally:
        vehicle.stop()


async def test_an_arm_is_refused_when_the_vehicle_does_not_take_the_fence(
    tmp_path: Path,
) -> None:
    """A polygon of more vertices than the vehicle holds: the upload refused (NO_SPACE),
    the Arm refused FAILED_PRECONDITION saying so, and the vehicle never armed."""
    steps = MAX_ITEMS + 1
    circle = [
        (100 * math.cos(2 * math.pi * k / steps), 100 * math.sin(2 * math.pi * k / steps))
        for k in range(steps)
    ]
    fence = Fence((polygon(circle),), ceiling_m=60.0)
    effects = tmp_path / "effects.jsonl"
    vehicle = sim_vehicle(effects)
    mobility = MavsdkMobility(vehicle.url, fence=fence)
    await mobility.start()
    try:

        async def ready() -> bool:
            if not mobility.connected:
                return False
            return (await mobility.GetFlightState(api.GetFlightStateRequest())).ready

        await eventually(ready, "vehicle ready", 20)
        with pytest.raises(StatusError) as refused:
            await mobility.Arm(api.ArmRequest())
        assert refused.value.code is grpc.StatusCode.FAILED_PRECONDITION
        assert "did not take the mission's fence (1 polygons, 0 circles)" in refused.value.message
        assert vehicle.state().fence is None and not vehicle.state().armed
        assert read_effects(effects) == []
    finally:
        await mobility.close()
        vehicle.stop()


async def test_the_vehicle_out_of_its_fence_returns_by_itself(tmp_path: Path) -> None:
    """The drone's backend sets GF_ACTION 3 (Return) beside the upload; flown out of the
    fence (a Goto straight to the backend, past the drone's own check), the sim vehicle
    returns by itself, as PX4 does: the autopilot's net under the drone's."""
    fence = Fence((square(100.0),), ceiling_m=60.0)
    effects = tmp_path / "effects.jsonl"
    vehicle = sim_vehicle(effects)
    mobility = MavsdkMobility(vehicle.url, fence=fence)
    await mobility.start()
    try:
        await eventually(lambda: vehicle.state().fence_action == 3, "GF_ACTION set", 20)

        async def ready() -> bool:
            if not mobility.connected:
                return False
            return (await mobility.GetFlightState(api.GetFlightStateRequest())).ready

        await eventually(ready, "vehicle ready", 20)
        await mobility.SetSpeed(api.SetSpeedRequest(speed_m_s=15.0))
        await mobility.Arm(api.ArmRequest())
        await mobility.Takeoff(api.TakeoffRequest(altitude_m=5.0))
        await eventually(lambda: vehicle.state().relative_altitude_m > 4.0, "5 m up", 20)
        out = offset(HOME, 300.0, 0.0)
        await mobility.Goto(
            api.GotoRequest(
                latitude_deg=out.latitude_deg,
                longitude_deg=out.longitude_deg,
                relative_altitude_m=5,
            )
        )

        def acted() -> list[dict[str, object]]:
            return [e for e in read_effects(effects) if e["effect"] == "fence_breach"]

        await eventually(acted, "the vehicle acting on its fence", 30)
        assert [e["action"] for e in acted()] == [3]
        assert vehicle.state().phase == "return"
    finally:
        await mobility.close()
        vehicle.stop()
