"""The sim vehicle as a real process, flown through MavsdkMobility."""

from __future__ import annotations

import asyncio
import ctypes
import math
import os
import platform
import signal
import socket
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path

import grpc
import pytest
from helpers.mobility import connected_mobility

from baton.drone.mobility import MavsdkMobility
from baton.rpc.errors import StatusError
from baton.sim_vehicle.kinematics import FlightParams, GeoPoint
from baton.sim_vehicle.server import SimVehicle
from baton.v1 import drone_api_pb2 as api

from .ground_station import GroundStation, mavlink
from .sim_process import SimProcess, eventually, start_sim

# tgkill(2) by architecture: sends a signal to one thread of a process.
SYS_TGKILL = {"x86_64": 234, "aarch64": 131}.get(platform.machine(), 234)

HOME = (47.397742, 8.545594, 488.0)
METRES_PER_DEG_LAT = 111_194.9


@pytest.fixture
async def sim() -> AsyncIterator[SimProcess]:
    vehicle = await start_sim("--speedup", "10", "--home", ",".join(map(str, HOME)))
    yield vehicle
    assert await vehicle.terminate() == 0


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


async def test_sigterm_taken_by_a_vehicle_thread_still_stops_it() -> None:
    """The kernel may hand a process's SIGTERM (a dead parent's, say) to any thread.

    Python runs handlers on the main thread only, and a main thread blocked in
    a lock without a timeout never learns of it: a sim vehicle once outlived
    its SIGKILLed testbed this way. ``tgkill`` picks the thread here.
    """
    vehicle = await start_sim()
    pid = vehicle.process.pid
    threads = [int(t) for t in os.listdir(f"/proc/{pid}/task") if int(t) != pid]
    assert threads, "the sim vehicle runs a thread per vehicle"

    async def main_thread_waits() -> bool:  # in its wait for a signal, not still starting
        wchan = Path(f"/proc/{pid}/task/{pid}/wchan").read_text()
        return "futex" in wchan or "poll" in wchan  # a lock, or the event loop's selector

    await eventually(main_thread_waits, "the main thread waiting")
    libc = ctypes.CDLL(None, use_errno=True)
    assert libc.syscall(SYS_TGKILL, pid, threads[0], signal.SIGTERM) == 0, ctypes.get_errno()
    try:
        assert await asyncio.wait_for(vehicle.process.wait(), 5.0) == 0
    finally:
        if vehicle.process.returncode is None:
            vehicle.process.kill()


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


async def test_unknown_command_gets_unsupported_and_params_work(sim: SimProcess) -> None:
    def exchange() -> tuple[int, float, float]:
        with GroundStation(sim.port) as gcs:
            gcs.say_hello()
            ack = gcs.command(mavlink.MAV_CMD_USER_1)
            gcs.link.mav.param_set_send(
                1, 1, b"MIS_TAKEOFF_ALT", 7.5, mavlink.MAV_PARAM_TYPE_REAL32
            )
            after_set = gcs.receive("PARAM_VALUE")
            gcs.link.mav.param_request_read_send(1, 1, b"MIS_TAKEOFF_ALT", -1)
            after_read = gcs.receive("PARAM_VALUE")
            return ack.result, after_set.param_value, after_read.param_value

    result, after_set, after_read = await asyncio.to_thread(exchange)
    assert result == mavlink.MAV_RESULT_UNSUPPORTED
    assert after_set == pytest.approx(7.5) and after_read == pytest.approx(7.5)


def _unused_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


async def test_unreachable_vehicle_is_unavailable_at_once() -> None:
    url = f"udpout://127.0.0.1:{_unused_udp_port()}"
    mobility = MavsdkMobility(url)
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
            assert url in error.value.message  # which vehicle; the wording is the backend's
        assert time.monotonic() - started < 1.0
    finally:
        await mobility.close()


@pytest.mark.parametrize(
    ("call", "request_", "field"),
    [
        ("Takeoff", api.TakeoffRequest(altitude_m=0), "altitude_m"),
        ("Takeoff", api.TakeoffRequest(altitude_m=math.nan), "altitude_m"),
        (
            "Goto",
            api.GotoRequest(latitude_deg=91, longitude_deg=8, relative_altitude_m=10),
            "latitude_deg",
        ),
        (
            "Goto",
            api.GotoRequest(latitude_deg=47, longitude_deg=-181, relative_altitude_m=10),
            "longitude_deg",
        ),
        (
            "Goto",
            api.GotoRequest(latitude_deg=math.nan, longitude_deg=8, relative_altitude_m=10),
            "latitude_deg",
        ),
        (
            "Goto",
            api.GotoRequest(latitude_deg=47, longitude_deg=8, relative_altitude_m=-1),
            "relative_altitude_m",
        ),
        # Issue 11: a Goto without a coordinate was flown to 0°N 0°E.
        ("Goto", api.GotoRequest(relative_altitude_m=10), "latitude_deg is missing"),
        (
            "Goto",
            api.GotoRequest(latitude_deg=47, relative_altitude_m=10),
            "longitude_deg is missing",
        ),
        # A SetSpeed's bytes read as a Goto: speed 5 becomes latitude 5, no longitude.
        (
            "Goto",
            api.GotoRequest.FromString(api.SetSpeedRequest(speed_m_s=5).SerializeToString()),
            "longitude_deg is missing",
        ),
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
        # Within a centimetre: the state may be read between the climb's last step and
        # the hold's (4.9993 m once, under a loaded full run).
        assert vehicle.state().relative_altitude_m == pytest.approx(5.0, abs=0.01)

        # In the air by MAVSDK's telemetry too (it trails the vehicle): a SetSpeed on
        # the ground is only kept for the next Goto (mobility.py SetSpeed).
        async def in_air() -> bool:
            return (await flight_state(mobility)).in_air

        await eventually(in_air, "MAVSDK's telemetry saying in the air")
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


async def test_mavsdk_is_ready_only_after_the_warmup() -> None:
    """MavsdkMobility asks for its streams and waits out the estimator, as with ArduPilot."""
    warmup_s = 20.0  # 2 s of wall time
    vehicle = SimVehicle(GeoPoint(*HOME), speedup=10, params=FlightParams(warmup_s=warmup_s))
    vehicle.start()
    mobility = MavsdkMobility(vehicle.url)
    await mobility.start()
    try:
        # Connected means position telemetry arrives: MAVSDK asked for it.
        await eventually(lambda: _connected(mobility), "vehicle connected")
        with pytest.raises(StatusError) as refused:
            await mobility.Arm(api.ArmRequest())
        assert refused.value.code is grpc.StatusCode.FAILED_PRECONDITION
        seen_not_ready: list[float] = []

        async def ready() -> bool:
            state = await flight_state(mobility)
            # Read after the reply: the health it reflects was sent before.
            sim_time_s = vehicle.state().time_s
            if state.ready:
                assert sim_time_s >= warmup_s, "ready before the estimator warmed up"
            else:
                seen_not_ready.append(sim_time_s)
            return state.ready

        await eventually(ready, "ready after the warm-up")
        assert seen_not_ready and min(seen_not_ready) < warmup_s
        # Every stream the backend reads was asked for and is streamed.
        asked = {
            mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,  # position
            mavlink.MAVLINK_MSG_ID_HOME_POSITION,  # home
            mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE,  # in air, landed state
            mavlink.MAVLINK_MSG_ID_BATTERY_STATUS,  # battery
            mavlink.MAVLINK_MSG_ID_SYS_STATUS,  # health
        }
        assert asked <= vehicle.streams().keys()
        await mobility.Arm(api.ArmRequest())
        await eventually(lambda: _armed(mobility), "armed")
    finally:
        await mobility.close()
        vehicle.stop()


async def _connected(mobility: MavsdkMobility) -> bool:
    return mobility.connected
