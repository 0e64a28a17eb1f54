"""Both SDK APIs (blocking ``baton.sdk``, asyncio ``baton.sdk.aio``) against one real
in-process gRPC server: the same requests and typed results, one call at a time, typed errors.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any

import grpc
import grpc.aio
import pytest
from waiting import eventually

from baton.rpc.methods import drone_api, rpc_of
from baton.rpc.mission import MISSION_TOKEN_ENV, MISSION_TOKEN_METADATA
from baton.sdk import ConcurrentCallError, DroneCallError, FlightState, Position, aio
from baton.sdk.drone import Drone
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_api_pb2_grpc, ring_pb2, ring_pb2_grpc

HERE = api.Position(
    latitude_deg=47.4, longitude_deg=8.5, absolute_altitude_m=500.0, relative_altitude_m=10.0
)


@dataclass
class FakeController:
    """The drone API and MissionDone of a controller, recording what it was sent."""

    received: list[tuple[str, Any, dict[str, str]]] = field(default_factory=list)
    # A call to this method waits for ``release`` (set from the test's thread or loop).
    hold: str = ""
    entered: threading.Event = field(default_factory=threading.Event)
    release: threading.Event = field(default_factory=threading.Event)
    # Methods refused with this status and message.
    refuse: dict[str, tuple[grpc.StatusCode, str]] = field(default_factory=dict)
    streams: int = 0  # ProgramCalls streams opened
    cancelled: int = 0  # held calls cancelled (the program gave up on them)

    async def answer(
        self, name: str, request: Any, context: grpc.aio.ServicerContext
    ) -> tuple[grpc.StatusCode, str] | None:
        """Records the call; the status it is refused with, if it is."""
        metadata = {k: v for k, v in context.invocation_metadata() or () if isinstance(v, str)}
        self.received.append((name, request, metadata))
        if name == self.hold:
            self.entered.set()
            try:
                await asyncio.to_thread(self.release.wait, 10)
            except asyncio.CancelledError:
                self.cancelled += 1
                raise
        return self.refuse.get(name)

    async def program_calls(
        self, calls: AsyncIterator[ring_pb2.ProgramCall], context: grpc.aio.ServicerContext
    ) -> AsyncIterator[ring_pb2.ProgramOutcome]:
        """ControllerRing.ProgramCalls as the controller answers it: each call as its
        unary method, a refusal as the call's failure."""
        self.streams += 1
        async for call in calls:
            found = drone_api()[call.method]
            service, name = rpc_of(call.method).split(".")
            refused = await self.answer(
                f"{service}.{name}", found.request_type.FromString(call.request), context
            )
            if refused is not None:
                code, message = refused
                failure = api.CallFailure(code=code.value[0], message=message)
                yield ring_pb2.ProgramOutcome(call=call.call, failure=failure)
            else:
                made = REPLIES.get(name)
                reply = made() if made is not None else reply_of(service, name)
                yield ring_pb2.ProgramOutcome(call=call.call, reply=reply.SerializeToString())


def servicers(fake: FakeController) -> list[tuple[Any, Callable[[Any, grpc.aio.Server], None]]]:
    """Servicers whose every method records its call and answers ``REPLIES``'s reply
    (or an empty one)."""

    def servicer(base: type, add: Callable[[Any, grpc.aio.Server], None]) -> tuple[Any, Any]:
        class Servicer(base):  # type: ignore[misc, valid-type]
            pass

        service = base.__name__.removesuffix("Servicer")
        for name in [n for n in vars(base) if not n.startswith("_")]:

            async def method(self: Any, request: Any, context: Any, name: str = name) -> Any:
                refused = await fake.answer(f"{service}.{name}", request, context)
                if refused is not None:
                    await context.abort(*refused)
                return REPLIES.get(name, lambda: reply_of(service, name))()

            setattr(Servicer, name, method)
        if service == "ControllerRing":

            async def program_calls(self: Any, calls: Any, context: Any) -> Any:
                async for outcome in fake.program_calls(calls, context):
                    yield outcome

            Servicer.ProgramCalls = program_calls
        return Servicer(), add

    return [
        servicer(
            drone_api_pb2_grpc.MobilityServicer, drone_api_pb2_grpc.add_MobilityServicer_to_server
        ),
        servicer(
            drone_api_pb2_grpc.CameraServicer, drone_api_pb2_grpc.add_CameraServicer_to_server
        ),
        servicer(drone_api_pb2_grpc.ClockServicer, drone_api_pb2_grpc.add_ClockServicer_to_server),
        servicer(
            ring_pb2_grpc.ControllerRingServicer, ring_pb2_grpc.add_ControllerRingServicer_to_server
        ),
    ]


def reply_of(service: str, method: str) -> Any:
    module = ring_pb2 if service == "ControllerRing" else api
    output = module.DESCRIPTOR.services_by_name[service].methods_by_name[method].output_type
    return getattr(module, output.name)()


REPLIES: dict[str, Callable[[], Any]] = {
    "GetPosition": lambda: api.GetPositionReply(position=HERE),
    "GetHome": lambda: api.GetHomeReply(home=HERE),
    "GetFlightState": lambda: api.GetFlightStateReply(
        armed=True, in_air=True, flight_mode="HOLD", ready=True, battery_percent=80.0
    ),
    "SetResolution": lambda: api.SetResolutionReply(width=640, height=480),
    "TakePicture": lambda: api.TakePictureReply(
        image=b"jpeg", format="jpeg", width=640, height=480, position=HERE, sequence=7
    ),
    "Now": lambda: api.NowReply(unix_time_s=1234.5),
}


@pytest.fixture
async def controller(monkeypatch: pytest.MonkeyPatch) -> AsyncIterator[tuple[str, FakeController]]:
    monkeypatch.setenv(MISSION_TOKEN_ENV, "the-token")
    fake = FakeController()
    server = grpc.aio.server()
    for servicer, add in servicers(fake):
        add(servicer, server)
    port = server.add_insecure_port("127.0.0.1:0")
    await server.start()
    yield f"127.0.0.1:{port}", fake
    fake.release.set()
    await server.stop(0)


class Api:
    """One of the two APIs, driven from the test's event loop (the blocking one in a thread,
    so that the server on this loop can answer it)."""

    def __init__(self, kind: str, address: str) -> None:
        self.kind = kind
        self.drone: Any = Drone(address) if kind == "sync" else aio.connect(address)

    async def call(self, path: str, *args: Any) -> Any:
        group, name = path.split(".")
        method = getattr(getattr(self.drone, group), name)
        if self.kind == "sync":
            return await asyncio.to_thread(method, *args)
        return await method(*args)

    async def close(self, error: str = "") -> None:
        if self.kind == "sync":
            await asyncio.to_thread(self.drone.close, error)
        else:
            await self.drone.close(error)


CONCURRENT = (
    r"Camera\.TakePicture called while Mobility\.GetPosition is pending.*one call at a time"
)
TARGET = Position(47.41, 8.51, 520.0, 20.0)
# (SDK method, its arguments, the RPC, the request it must send, the result it must give)
CALLS: list[tuple[str, tuple[Any, ...], str, Any, Any]] = [
    ("mobility.arm", (), "Mobility.Arm", api.ArmRequest(), None),
    ("mobility.disarm", (), "Mobility.Disarm", api.DisarmRequest(), None),
    ("mobility.takeoff", (12.5,), "Mobility.Takeoff", api.TakeoffRequest(altitude_m=12.5), None),
    (
        "mobility.goto",
        (TARGET, 15.0),
        "Mobility.Goto",
        api.GotoRequest(latitude_deg=47.41, longitude_deg=8.51, relative_altitude_m=15.0),
        None,
    ),
    (
        "mobility.goto",
        (TARGET,),
        "Mobility.Goto",
        api.GotoRequest(latitude_deg=47.41, longitude_deg=8.51, relative_altitude_m=20.0),
        None,
    ),
    ("mobility.set_speed", (4.0,), "Mobility.SetSpeed", api.SetSpeedRequest(speed_m_s=4.0), None),
    ("mobility.hold", (), "Mobility.Hold", api.HoldRequest(), None),
    ("mobility.land", (), "Mobility.Land", api.LandRequest(), None),
    ("mobility.return_to_launch", (), "Mobility.ReturnToLaunch", api.ReturnToLaunchRequest(), None),
    (
        "mobility.position",
        (),
        "Mobility.GetPosition",
        api.GetPositionRequest(),
        Position(47.4, 8.5, 500.0, 10.0),
    ),
    (
        "mobility.home",
        (),
        "Mobility.GetHome",
        api.GetHomeRequest(),
        Position(47.4, 8.5, 500.0, 10.0),
    ),
    (
        "mobility.flight_state",
        (),
        "Mobility.GetFlightState",
        api.GetFlightStateRequest(),
        FlightState(True, True, "HOLD", "", 80.0, True),
    ),
    (
        "camera.set_resolution",
        (640, 480),
        "Camera.SetResolution",
        api.SetResolutionRequest(width=640, height=480),
        (640, 480),
    ),
    ("clock.sleep", (2.0,), "Clock.Sleep", api.SleepRequest(seconds=2.0), None),
    ("clock.now", (), "Clock.Now", api.NowRequest(), 1234.5),
]


@pytest.mark.parametrize("kind", ["sync", "async"])
async def test_every_call_sends_its_request_with_the_token_and_gives_a_typed_result(
    kind: str, controller: tuple[str, FakeController]
) -> None:
    address, fake = controller
    sdk = Api(kind, address)
    for method, args, rpc, request, result in CALLS:
        assert await sdk.call(method, *args) == result, method
        name, sent, metadata = fake.received[-1]
        assert (name, sent) == (rpc, request), method
        assert metadata[MISSION_TOKEN_METADATA] == "the-token"
    assert fake.streams == 1  # every call a message on the one stream of calls
    picture = await sdk.call("camera.take_picture")
    assert (picture.image, picture.sequence, picture.position) == (b"jpeg", 7, CALLS[9][4])
    await sdk.close("ValueError: gave up")
    assert fake.received[-1][:2] == (
        "ControllerRing.MissionDone",
        ring_pb2.MissionDoneRequest(failed=True, error="ValueError: gave up"),
    )


@pytest.mark.parametrize("kind", ["sync", "async"])
async def test_a_refused_call_raises_drone_call_error_naming_the_rpc_and_status(
    kind: str, controller: tuple[str, FakeController]
) -> None:
    address, fake = controller
    fake.refuse["Mobility.Arm"] = (grpc.StatusCode.FAILED_PRECONDITION, "not armable: no GPS")
    sdk = Api(kind, address)
    with pytest.raises(DroneCallError) as raised:
        await sdk.call("mobility.arm")
    assert raised.value.rpc == "Mobility.Arm"
    assert raised.value.code is grpc.StatusCode.FAILED_PRECONDITION
    assert raised.value.details == "not armable: no GPS"
    assert str(raised.value) == "Mobility.Arm failed with FAILED_PRECONDITION: not armable: no GPS"
    # The failed call does not hold the next one back.
    assert await sdk.call("clock.now") == 1234.5
    await sdk.close()


async def test_the_async_api_refuses_a_second_call_while_one_is_pending(
    controller: tuple[str, FakeController],
) -> None:
    address, fake = controller
    fake.hold = "Mobility.GetPosition"
    async with aio.connect(address) as drone:
        first = asyncio.create_task(drone.mobility.position())
        await asyncio.to_thread(fake.entered.wait, 10)
        with pytest.raises(
            ConcurrentCallError,
            match=CONCURRENT,
        ):
            await drone.camera.take_picture()
        assert [name for name, _, _ in fake.received] == ["Mobility.GetPosition"]
        fake.release.set()
        assert await first == Position(47.4, 8.5, 500.0, 10.0)
        assert await drone.clock.now() == 1234.5


async def test_a_cancelled_async_call_lets_the_next_one_through(
    controller: tuple[str, FakeController],
) -> None:
    address, fake = controller
    fake.hold = "Clock.Sleep"
    async with aio.connect(address) as drone:
        held = asyncio.create_task(drone.clock.sleep(60))
        await asyncio.to_thread(fake.entered.wait, 10)
        held.cancel()
        with pytest.raises(asyncio.CancelledError):
            await held
        # The controller sees the call given up (its stream cancelled: a real one logs
        # the give-up), and the next call goes on a new stream.
        await eventually(lambda: fake.cancelled == 1, "the held call cancelled at the server")
        fake.release.set()
        assert await drone.clock.now() == 1234.5
        assert (fake.streams, fake.cancelled) == (2, 1)


async def test_the_blocking_api_refuses_a_second_call_from_another_thread(
    controller: tuple[str, FakeController],
) -> None:
    address, fake = controller
    fake.hold = "Mobility.GetPosition"
    drone = Drone(address)
    first = asyncio.ensure_future(asyncio.to_thread(drone.mobility.position))
    await asyncio.to_thread(fake.entered.wait, 10)
    with pytest.raises(
        ConcurrentCallError,
        match=CONCURRENT,
    ):
        await asyncio.to_thread(drone.camera.take_picture)
    fake.release.set()
    assert await first == Position(47.4, 8.5, 500.0, 10.0)
    assert await asyncio.to_thread(drone.clock.now) == 1234.5
    await asyncio.to_thread(drone.close)


async def test_exiting_async_with_on_an_error_tells_the_controller_why(
    controller: tuple[str, FakeController],
) -> None:
    address, fake = controller
    with pytest.raises(RuntimeError, match="lost the picture"):
        async with aio.connect(address) as drone:
            await drone.mobility.arm()
            raise RuntimeError("lost the picture")
    name, request, _ = fake.received[-1]
    assert name == "ControllerRing.MissionDone"
    assert request.failed and "lost the picture" in request.error
