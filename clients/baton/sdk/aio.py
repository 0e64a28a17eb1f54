"""The asyncio API, in MAVSDK-Python's style: the same calls as ``drone.py``, awaited.

    from baton.sdk.aio import connect

    async def mission(drone):  # run.py gives it a connected Drone
        await drone.mobility.arm()
        await drone.mobility.takeoff(10)

    async with connect("127.0.0.1:7100") as drone:  # or connect on one's own
        ...

The rules are the blocking API's: one call at a time (a second call while one
is pending, from another task, raises ``ConcurrentCallError``: every replica
must replay the program's calls in the same order), and a failed call raises
``DroneCallError`` naming the RPC and its status. The calls themselves are in
``calls.py``; the transport is ``grpc.aio``.
"""

from __future__ import annotations

import asyncio
import itertools
from types import TracebackType
from typing import Any, TypeVar

import grpc
import grpc.aio

from baton.rpc.channels import aio_channel
from baton.sdk import calls
from baton.sdk.drone import mission_token_metadata
from baton.sdk.errors import DroneCallError, call_error, concurrent_call_error
from baton.sdk.types import FlightState, Picture, Position

ResultT = TypeVar("ResultT")


class _Caller:
    """Sends ``calls.Call``s over an asyncio channel, one at a time, with typed errors,
    on the stream of calls kept open to the controller (as ``drone.py``'s)."""

    def __init__(
        self, channel: grpc.aio.Channel, metadata: tuple[tuple[str, str], ...] = ()
    ) -> None:
        self._pending = ""  # the call awaiting its reply, if one is
        self._methods = calls.Methods(channel)
        self._stream: Any = None  # the stream of calls, once opened
        self._numbers = itertools.count(1)
        self.metadata = metadata  # the mission token (baton.rpc.mission), if given

    async def __call__(self, call: calls.Call[ResultT]) -> ResultT:
        if self._pending:
            raise concurrent_call_error(call.rpc, self._pending)
        self._pending = call.rpc
        try:
            return await self._on_stream(call)
        finally:
            self._pending = ""

    async def _on_stream(self, call: calls.Call[ResultT]) -> ResultT:
        if self._stream is None:
            # No deadline: a PASSIVE controller holds the call until it may answer.
            self._stream = self._methods.program_calls()(
                metadata=self.metadata, wait_for_ready=True
            )
        stream = self._stream
        number = next(self._numbers)
        try:
            await stream.write(calls.on_stream(number, call))
            outcome = await stream.read()
        except grpc.RpcError as exc:
            self._stream = None
            raise call_error(call.rpc, exc) from None
        except asyncio.InvalidStateError:  # the stream had ended, without an error
            self._stream = None
            raise calls.stream_ended(call) from None
        except BaseException:
            # Cancelled while waiting: the controller must see the call given up (the
            # stream cancelled), not answer it on the stream the next call would use.
            self.end_stream()
            raise
        if outcome is grpc.aio.EOF:
            self._stream = None
            raise calls.stream_ended(call)
        return calls.result_of(call, number, outcome)

    def end_stream(self) -> None:
        """Cancels the stream of calls, if one is open (the next call opens another)."""
        if self._stream is not None:
            stream, self._stream = self._stream, None
            stream.cancel()

    async def send(self, call: calls.Call[ResultT], **options: Any) -> ResultT:
        """Sends ``call`` as a unary call, whatever else is pending (the end of the program)."""
        try:
            reply = await self._methods[call](call.request, metadata=self.metadata, **options)
        except grpc.RpcError as exc:
            raise call_error(call.rpc, exc) from None
        return call.result(reply)


class Mobility:
    """Movement: arm, take off, go to, land; position and flight state."""

    def __init__(self, call: _Caller) -> None:
        self._call = call

    async def arm(self) -> None:
        """Arms the motors."""
        await self._call(calls.arm())

    async def disarm(self) -> None:
        """Disarms the motors."""
        await self._call(calls.disarm())

    async def takeoff(self, altitude_m: float) -> None:
        """Starts climbing to ``altitude_m`` above home."""
        await self._call(calls.takeoff(altitude_m))

    async def goto(self, target: Position, relative_altitude_m: float | None = None) -> None:
        """Starts flying to ``target`` (at its relative altitude unless one is given)."""
        await self._call(calls.goto(target, relative_altitude_m))

    async def set_speed(self, speed_m_s: float) -> None:
        """Sets the cruise speed of later gotos."""
        await self._call(calls.set_speed(speed_m_s))

    async def hold(self) -> None:
        """Stops and holds position."""
        await self._call(calls.hold())

    async def land(self) -> None:
        """Lands where the vehicle is."""
        await self._call(calls.land())

    async def return_to_launch(self) -> None:
        """Flies home and lands."""
        await self._call(calls.return_to_launch())

    async def position(self) -> Position:
        """The vehicle's latest position."""
        return await self._call(calls.position())

    async def home(self) -> Position:
        """The home position."""
        return await self._call(calls.home())

    async def flight_state(self) -> FlightState:
        """Armed, in air, mode, battery, readiness."""
        return await self._call(calls.flight_state())


class Camera:
    """The on-board camera."""

    def __init__(self, call: _Caller) -> None:
        self._call = call

    async def set_resolution(self, width: int, height: int) -> tuple[int, int]:
        """Sets the picture size; returns the size in use."""
        return await self._call(calls.set_resolution(width, height))

    async def take_picture(self) -> Picture:
        """Takes a picture."""
        return await self._call(calls.take_picture())


class Gimbal:
    """Where the camera points: a region of interest, until cleared."""

    def __init__(self, call: _Caller) -> None:
        self._call = call

    async def set_roi_location(
        self, target: Position, relative_altitude_m: float | None = None
    ) -> None:
        """Points the camera at ``target`` (at its relative altitude unless one is given)."""
        await self._call(calls.set_roi_location(target, relative_altitude_m))

    async def clear_roi(self) -> None:
        """Clears the region of interest."""
        await self._call(calls.clear_roi())


class Clock:
    """Mission time: sleeps really only while the controller is the active master."""

    def __init__(self, call: _Caller) -> None:
        self._call = call

    async def sleep(self, seconds: float) -> None:
        """Sleeps ``seconds`` of mission time (at once while replaying)."""
        await self._call(calls.sleep(seconds))

    async def now(self) -> float:
        """Mission time, Unix seconds; the same on every replica."""
        return await self._call(calls.now())


class Drone:
    """A drone, as seen through the local mission controller; every call is awaited.

    ``channel``: one to use instead of a connection to ``address``; ``token``: the
    mission token, if not this program's ``BATON_MISSION_TOKEN``.
    """

    def __init__(
        self, address: str, channel: grpc.aio.Channel | None = None, token: str | None = None
    ) -> None:
        self.address = address
        self._channel = aio_channel(address) if channel is None else channel
        self._call = _Caller(self._channel, mission_token_metadata(token))
        self.mobility = Mobility(self._call)
        self.camera = Camera(self._call)
        self.gimbal = Gimbal(self._call)
        self.clock = Clock(self._call)

    async def close(self, error: str = "") -> None:
        """Tells the controller the mission has ended, then closes the channel."""
        try:
            await self._call.send(calls.mission_done(error), timeout=calls.MISSION_DONE_TIMEOUT_S)
        except DroneCallError:
            pass  # the controller is gone: nothing left to flush to
        finally:
            self._call.end_stream()
            await self._channel.close()

    async def __aenter__(self) -> Drone:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close(error=repr(exc) if exc is not None else "")


def connect(address: str) -> Drone:
    """A Drone through the controller at ``host:port``, for ``async with``."""
    return Drone(address)
