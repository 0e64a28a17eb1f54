"""The drone API's calls, written once: what each sends and what its reply means.

The blocking API (``drone.py``) and the asyncio one (``aio.py``) are thin
faces over this table: a method there builds a ``Call`` here and hands it to
its transport, which sends ``request`` to ``path`` and returns
``result(reply)``. So a call's name, its request and the typed result it
gives are the same in both, and the one-call-at-a-time rule and the error
mapping (``errors.py``) live in one place each.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Generic, NamedTuple, TypeVar

import grpc
from google.protobuf.message import Message

from baton.rpc.errors import status_of
from baton.rpc.methods import method, path
from baton.sdk.errors import DroneCallError
from baton.sdk.types import FlightState, Picture, Position
from baton.v1 import drone_api_pb2 as api
from baton.v1 import ring_pb2

ResultT = TypeVar("ResultT")


class Call(NamedTuple, Generic[ResultT]):
    """One call of the drone API: ``rpc`` ("Mobility.Takeoff") names it in errors.

    A named tuple: a replay makes some 100,000 calls a second, and a frozen
    dataclass cost a few microseconds of each."""

    rpc: str
    path: str  # the gRPC method, "/baton.v1.Mobility/Takeoff"
    request: Message
    reply_type: type[Message]
    result: Callable[[Any], ResultT]


# The drone-API calls travel as messages on one stream the program keeps open to
# its controller (ring.proto ProgramCalls): a unary call sets up an HTTP/2 stream
# and its call state at both ends each time (docs/design.md, "The proxy path").
PROGRAM_CALLS = path("ControllerRing.ProgramCalls")


def on_stream(number: int, call: Call[Any]) -> ring_pb2.ProgramCall:
    """``call`` as the ``number``-th message of the program's stream."""
    return ring_pb2.ProgramCall(
        call=number, method=call.path, request=call.request.SerializeToString()
    )


def result_of(call: Call[ResultT], number: int, outcome: ring_pb2.ProgramOutcome) -> ResultT:
    """The result of the ``number``-th call on the stream from its ``outcome``, or the
    ``DroneCallError`` its unary call would have raised."""
    if outcome.call != number:
        raise DroneCallError(
            call.rpc,
            grpc.StatusCode.INTERNAL,
            f"the controller answered call {outcome.call} on the stream, expected {number}",
        )
    if outcome.HasField("failure"):
        raise DroneCallError(call.rpc, status_of(outcome.failure.code), outcome.failure.message)
    return call.result(call.reply_type.FromString(outcome.reply))


def stream_ended(call: Call[Any]) -> DroneCallError:
    """The error of a call whose stream the controller ended before its outcome."""
    return DroneCallError(
        call.rpc,
        grpc.StatusCode.UNAVAILABLE,
        "the controller ended the stream of calls before this call's outcome",
    )


class Methods:
    """A channel's callable for each call's gRPC path, made on first use, and for the
    stream of calls: the same for a blocking and an asyncio channel (and ``baton
    replay``'s), whose ``unary_unary`` and ``stream_stream`` agree."""

    def __init__(self, channel: Any) -> None:
        self._channel = channel
        self._methods: dict[str, Any] = {}

    def program_calls(self) -> Any:
        """The multi-callable that opens the stream of calls (ring.proto ProgramCalls)."""
        return self._channel.stream_stream(
            PROGRAM_CALLS,
            request_serializer=ring_pb2.ProgramCall.SerializeToString,
            response_deserializer=ring_pb2.ProgramOutcome.FromString,
        )

    def __getitem__(self, call: Call[Any]) -> Any:
        method = self._methods.get(call.path)
        if method is None:
            method = self._methods[call.path] = self._channel.unary_unary(
                call.path,
                request_serializer=type(call.request).SerializeToString,
                response_deserializer=call.reply_type.FromString,
            )
        return method


def _nothing(reply: Message) -> None:
    return None


def _call(rpc: str, request: Message, result: Callable[[Any], ResultT]) -> Call[ResultT]:
    """``rpc``'s call; its path and reply class come from the contracts (rpc/methods.py)."""
    found = method(rpc)
    return Call(rpc, found.path, request, found.reply_type, result)


def _command(rpc: str, request: Message) -> Call[None]:
    """A call whose reply says nothing beyond its success."""
    return _call(rpc, request, _nothing)


# Mobility ------------------------------------------------------------------------------


def arm() -> Call[None]:
    """Arms the motors."""
    return _command("Mobility.Arm", api.ArmRequest())


def disarm() -> Call[None]:
    """Disarms the motors."""
    return _command("Mobility.Disarm", api.DisarmRequest())


def takeoff(altitude_m: float) -> Call[None]:
    """Starts climbing to ``altitude_m`` above home."""
    return _command("Mobility.Takeoff", api.TakeoffRequest(altitude_m=altitude_m))


def goto(target: Position, relative_altitude_m: float | None = None) -> Call[None]:
    """Starts flying to ``target`` (at its relative altitude unless one is given)."""
    altitude = target.relative_altitude_m if relative_altitude_m is None else relative_altitude_m
    request = api.GotoRequest(
        latitude_deg=target.latitude_deg,
        longitude_deg=target.longitude_deg,
        relative_altitude_m=altitude,
    )
    return _command("Mobility.Goto", request)


def set_speed(speed_m_s: float) -> Call[None]:
    """Sets the cruise speed of later gotos."""
    return _command("Mobility.SetSpeed", api.SetSpeedRequest(speed_m_s=speed_m_s))


def hold() -> Call[None]:
    """Stops and holds position."""
    return _command("Mobility.Hold", api.HoldRequest())


def land() -> Call[None]:
    """Lands where the vehicle is."""
    return _command("Mobility.Land", api.LandRequest())


def return_to_launch() -> Call[None]:
    """Flies home and lands."""
    return _command("Mobility.ReturnToLaunch", api.ReturnToLaunchRequest())


def position() -> Call[Position]:
    """The vehicle's latest position."""
    return _call(
        "Mobility.GetPosition",
        api.GetPositionRequest(),
        lambda reply: Position.from_proto(reply.position),
    )


def home() -> Call[Position]:
    """The home position."""
    return _call(
        "Mobility.GetHome", api.GetHomeRequest(), lambda reply: Position.from_proto(reply.home)
    )


def flight_state() -> Call[FlightState]:
    """Armed, in air, mode, battery, readiness."""
    return _call("Mobility.GetFlightState", api.GetFlightStateRequest(), FlightState.from_proto)


# Camera --------------------------------------------------------------------------------


def set_resolution(width: int, height: int) -> Call[tuple[int, int]]:
    """Sets the picture size; the result is the size in use."""
    return _call(
        "Camera.SetResolution",
        api.SetResolutionRequest(width=width, height=height),
        lambda reply: (reply.width, reply.height),
    )


def take_picture() -> Call[Picture]:
    """Takes a picture."""
    return _call("Camera.TakePicture", api.TakePictureRequest(), Picture.from_proto)


# Gimbal --------------------------------------------------------------------------------


def set_roi_location(target: Position, relative_altitude_m: float | None = None) -> Call[None]:
    """Points the camera at ``target`` (at its relative altitude unless one is given)
    until the region of interest is cleared or set again."""
    altitude = target.relative_altitude_m if relative_altitude_m is None else relative_altitude_m
    request = api.SetRoiLocationRequest(
        latitude_deg=target.latitude_deg,
        longitude_deg=target.longitude_deg,
        relative_altitude_m=altitude,
    )
    return _command("Gimbal.SetRoiLocation", request)


def clear_roi() -> Call[None]:
    """Clears the region of interest."""
    return _command("Gimbal.ClearRoi", api.ClearRoiRequest())


# Clock ---------------------------------------------------------------------------------


def sleep(seconds: float) -> Call[None]:
    """Sleeps ``seconds`` of mission time (at once while replaying)."""
    return _command("Clock.Sleep", api.SleepRequest(seconds=seconds))


def now() -> Call[float]:
    """Mission time, Unix seconds; the same on every replica."""
    return _call("Clock.Now", api.NowRequest(), lambda reply: reply.unix_time_s)


# The end of the program ----------------------------------------------------------------

# How long the controller is given to flush the log when the program ends.
MISSION_DONE_TIMEOUT_S = 10.0


def mission_done(error: str = "") -> Call[None]:
    """Tells the controller the program has ended (``error``: why it failed, if it did)."""
    return _command(
        "ControllerRing.MissionDone",
        ring_pb2.MissionDoneRequest(failed=bool(error), error=error),
    )
