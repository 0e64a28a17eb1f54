"""The sim vehicle as a real process, flown through MavsdkMobility."""

from __future__ import annotations

import asyncio
import math
import socket
import time
from collections.abc import AsyncIterator, Awaitable, Callable

import grpc
import pytest
from pymavlink import mavutil

from baton.drone.mobility import MavsdkMobility
from baton.rpc.errors import StatusError
from baton.sim_vehicle.kinematics import GeoPoint
from baton.sim_vehicle.server import SimVehicle
from baton.v1 import drone_api_pb2 as api

from .sim_process import SimProcess, eventually, start_sim

HOME = (47.397742, 8.545594, 488.0)
METRES_PER_DEG_LAT = 111_194.9


@pytest.fixture
async def sim() -> AsyncIterator[SimProcess]:
    vehicle = await start_sim("--speedup", "10", "--home", ",".join(map(str, HOME)))
    yield vehicle
    assert await vehicle.terminate() == 0


async def connected_mobility(url: str) -> MavsdkMobility:
    mobility = MavsdkMobility(url)
    await mobility.start()

    async def ready() -> bool:
        return (
            mobility.connected
            and (await mobility.GetFlightState(api.GetFlightStateRequest())).ready
        )

    await eventually(ready, "vehicle connected and ready")
    return mobility


async def position(mobility: MavsdkMobility) -> api.Position:
    return (await mobility.GetPosition(api.GetPositionRequest())).position


async def flight_state(mobility: MavsdkMobility) -> api.GetFlightStateReply:
    return await mobility.GetFlightState(api.GetFlightStateRequest())


async def test_arm_takeoff_goto_land(sim: SimProcess) -> None:
    mobility = await connected_mobility(sim.url)
    try:
        home = (await mobility.GetHome(api.GetHomeRequest())).home
        assert home.latitude_deg == pytest.approx(HOME[0])
        assert home.absolute_altitude_m == pytest.approx(HOME[2], abs=0.01)

        # The autopilot's refusal comes back with MAVSDK's reason.
        with pytest.raises(StatusError) as refused:
            await mobility.Takeoff(api.TakeoffRequest(altitude_m=10))
        assert refused.value.code is grpc.StatusCode.FAILED_PRECONDITION
        assert "COMMAND_DENIED" in refused.value.message

        await mobility.Arm(api.ArmRequest())
        await eventually(lambda: _armed(mobility), "armed")
        await mobility.Takeoff(api.TakeoffRequest(altitude_m=10))

        async def at_altitude() -> bool:
            state = await flight_state(mobility)
            return (
                await position(mobility)
            ).relative_altitude_m > 9.8 and state.flight_mode == "HOLD"

        await eventually(at_altitude, "10 m and holding")
        assert (await flight_state(mobility)).in_air

        target_lat = home.latitude_deg + 50 / METRES_PER_DEG_LAT
        await mobility.Goto(
            api.GotoRequest(
                latitude_deg=target_lat, longitude_deg=home.longitude_deg, relative_altitude_m=10
            )
        )

        async def at_target() -> bool:
            here = await position(mobility)
            north_m = (here.latitude_deg - home.latitude_deg) * METRES_PER_DEG_LAT
            return abs(north_m - 50) < 0.5 and abs(here.relative_altitude_m - 10) < 0.5

        await eventually(at_target, "50 m north of home")

        await mobility.Land(api.LandRequest())

        async def landed() -> bool:
            state = await flight_state(mobility)
            return not state.armed and not state.in_air and state.landed_state == "ON_GROUND"

        await eventually(landed, "landed and disarmed")
        assert (await position(mobility)).relative_altitude_m < 0.2
    finally:
        await mobility.close()


async def _armed(mobility: MavsdkMobility) -> bool:
    return (await flight_state(mobility)).armed


async def test_two_vehicles_do_not_cross_talk() -> None:
    first, second = await asyncio.gather(start_sim("--speedup", "10"), start_sim("--speedup", "10"))
    assert first.port != second.port
    mobilities = [await connected_mobility(v.url) for v in (first, second)]
    try:
        await mobilities[0].Arm(api.ArmRequest())
        await mobilities[0].Takeoff(api.TakeoffRequest(altitude_m=5))

        async def first_up() -> bool:
            return (await position(mobilities[0])).relative_altitude_m > 4.8

        await eventually(first_up, "first vehicle at 5 m")
        other = await flight_state(mobilities[1])
        assert not other.armed and not other.in_air
        assert (await position(mobilities[1])).relative_altitude_m == pytest.approx(0.0, abs=0.05)
    finally:
        for mobility in mobilities:
            await mobility.close()
        assert await first.terminate() == 0
        assert await second.terminate() == 0


async def test_sigterm_exits_zero_promptly() -> None:
    vehicle = await start_sim()
    started = time.monotonic()
    assert await vehicle.terminate(timeout_s=3.0) == 0
    assert time.monotonic() - started < 1.0


async def test_url_file_is_written(tmp_path) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "vehicle.url"
    vehicle = await start_sim("--url-file", str(path))
    try:
        await eventually(lambda: _exists(path), "url file")
        assert path.read_text().strip() == vehicle.url
    finally:
        assert await vehicle.terminate() == 0


async def _exists(path) -> bool:  # type: ignore[no-untyped-def]
    return bool(path.exists())


def _pymavlink_client(port: int) -> mavutil.mavudp:
    link = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255)
    link.mav.heartbeat_send(
        mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0
    )
    assert link.recv_match(type="HEARTBEAT", blocking=True, timeout=5) is not None
    return link


async def test_unknown_command_gets_unsupported_and_params_work(sim: SimProcess) -> None:
    def exchange() -> tuple[int, float, float]:
        link = _pymavlink_client(sim.port)
        try:
            link.mav.command_long_send(1, 1, mavutil.mavlink.MAV_CMD_USER_1, 0, 0, 0, 0, 0, 0, 0, 0)
            ack = link.recv_match(
                type="COMMAND_ACK",
                blocking=True,
                timeout=5,
                condition=f"COMMAND_ACK.command=={mavutil.mavlink.MAV_CMD_USER_1}",
            )
            link.mav.param_set_send(
                1, 1, b"MIS_TAKEOFF_ALT", 7.5, mavutil.mavlink.MAV_PARAM_TYPE_REAL32
            )
            after_set = link.recv_match(type="PARAM_VALUE", blocking=True, timeout=5)
            link.mav.param_request_read_send(1, 1, b"MIS_TAKEOFF_ALT", -1)
            after_read = link.recv_match(type="PARAM_VALUE", blocking=True, timeout=5)
            return ack.result, after_set.param_value, after_read.param_value
        finally:
            link.close()

    result, after_set, after_read = await asyncio.to_thread(exchange)
    assert result == mavutil.mavlink.MAV_RESULT_UNSUPPORTED
    assert after_set == pytest.approx(7.5) and after_read == pytest.approx(7.5)


def _unused_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


async def test_unreachable_vehicle_is_unavailable_at_once() -> None:
    mobility = MavsdkMobility(f"udpout://127.0.0.1:{_unused_udp_port()}")
    started = time.monotonic()
    await mobility.start()
    try:
        assert not mobility.connected
        calls: list[Callable[[], Awaitable[object]]] = [
            lambda: mobility.Arm(api.ArmRequest()),
            lambda: mobility.Takeoff(api.TakeoffRequest(altitude_m=10)),
            lambda: mobility.GetPosition(api.GetPositionRequest()),
            lambda: mobility.GetFlightState(api.GetFlightStateRequest()),
        ]
        for call in calls:
            with pytest.raises(StatusError) as error:
                await call()
            assert error.value.code is grpc.StatusCode.UNAVAILABLE
            assert "not connected" in error.value.message
        assert time.monotonic() - started < 1.0
    finally:
        await mobility.close()


@pytest.mark.parametrize(
    ("call", "request_", "field"),
    [
        ("Takeoff", api.TakeoffRequest(altitude_m=0), "altitude_m"),
        ("Takeoff", api.TakeoffRequest(altitude_m=math.nan), "altitude_m"),
        ("Goto", api.GotoRequest(latitude_deg=91, relative_altitude_m=10), "latitude_deg"),
        ("Goto", api.GotoRequest(longitude_deg=-181, relative_altitude_m=10), "longitude_deg"),
        ("Goto", api.GotoRequest(latitude_deg=math.nan, relative_altitude_m=10), "latitude_deg"),
        ("Goto", api.GotoRequest(relative_altitude_m=-1), "relative_altitude_m"),
        ("SetSpeed", api.SetSpeedRequest(speed_m_s=0), "speed_m_s"),
    ],
)
async def test_bad_arguments_are_invalid(call: str, request_: object, field: str) -> None:
    mobility = MavsdkMobility("udpout://127.0.0.1:9")  # never started: arguments are checked first
    with pytest.raises(StatusError) as error:
        await getattr(mobility, call)(request_)
    assert error.value.code is grpc.StatusCode.INVALID_ARGUMENT
    assert field in error.value.message


async def test_speed_hold_and_return_to_launch_in_process() -> None:
    """The in-process SimVehicle API, flown through the other Mobility commands."""
    vehicle = SimVehicle(GeoPoint(*HOME), speedup=20)
    vehicle.start()
    mobility = await connected_mobility(vehicle.url)
    try:

        async def phase(name: str) -> bool:
            return vehicle.state().phase == name

        await mobility.Arm(api.ArmRequest())
        await mobility.Takeoff(api.TakeoffRequest(altitude_m=5))
        await eventually(lambda: phase("hold"), "holding after takeoff")
        assert vehicle.state().relative_altitude_m == pytest.approx(5.0)

        await mobility.SetSpeed(api.SetSpeedRequest(speed_m_s=8))
        assert vehicle.state().speed_m_s == pytest.approx(8.0)
        far_lat = HOME[0] + 500 / METRES_PER_DEG_LAT
        await mobility.Goto(
            api.GotoRequest(latitude_deg=far_lat, longitude_deg=HOME[1], relative_altitude_m=5)
        )

        async def on_the_way() -> bool:
            return vehicle.state().phase == "goto" and vehicle.state().latitude_deg > HOME[0]

        await eventually(on_the_way, "flying the goto")
        await mobility.Hold(api.HoldRequest())
        await eventually(lambda: phase("hold"), "holding mid-way")
        assert HOME[0] < vehicle.state().latitude_deg < far_lat

        await mobility.ReturnToLaunch(api.ReturnToLaunchRequest())
        assert (await flight_state(mobility)).flight_mode in ("HOLD", "RETURN_TO_LAUNCH")

        async def home_and_down() -> bool:
            state = vehicle.state()
            return not state.armed and state.latitude_deg == pytest.approx(HOME[0], abs=1e-7)

        await eventually(home_and_down, "back home, landed, disarmed")
    finally:
        await mobility.close()
        vehicle.stop()
