"""The ``Drone`` handle: mobility, camera, gimbal and clock, each call blocking until it returns.

The calls themselves are in ``calls.py``, shared with the asyncio API (``aio.py``).
"""

from __future__ import annotations

import itertools
import os
import queue
import threading
from types import TracebackType
from typing import Any, TypeVar

import grpc

from baton.rpc.channels import sync_channel
from baton.rpc.mission import MISSION_TOKEN_ENV, MISSION_TOKEN_METADATA
from baton.sdk import calls
from baton.sdk.errors import DroneCallError, call_error, concurrent_call_error
from baton.sdk.types import FlightState, Picture, Position
from baton.v1 import ring_pb2

ResultT = TypeVar("ResultT")


class _Caller:
    """Sends ``calls.Call``s over a blocking channel, one at a time, with typed errors.

    The drone-API calls go as messages on the stream of calls kept open to the
    controller (``calls.PROGRAM_CALLS``), opened on the first call and again
    after one that failed with it."""

    def __init__(self, channel: grpc.Channel, metadata: tuple[tuple[str, str], ...] = ()) -> None:
        self._lock = threading.Lock()
        self._pending = ""
        self._methods = calls.Methods(channel)
        self._stream: tuple[queue.SimpleQueue[ring_pb2.ProgramCall | None], Any] | None = None
        self._numbers = itertools.count(1)
        self.metadata = metadata  # the mission token (baton.rpc.mission), if given

    def __call__(self, call: calls.Call[ResultT]) -> ResultT:
        if not self._lock.acquire(blocking=False):
            raise concurrent_call_error(call.rpc, self._pending)
        self._pending = call.rpc
        try:
            return self._on_stream(call)
        finally:
            self._lock.release()

    def _on_stream(self, call: calls.Call[ResultT]) -> ResultT:
        if self._stream is None:
            requests: queue.SimpleQueue[ring_pb2.ProgramCall | None] = queue.SimpleQueue()
            # No deadline: a PASSIVE controller holds the call until it may answer.
            outcomes = self._methods.program_calls()(
                iter(requests.get, None), metadata=self.metadata, wait_for_ready=True
            )
            self._stream = (requests, outcomes)
        requests, outcomes = self._stream
        number = next(self._numbers)
        requests.put(calls.on_stream(number, call))
        try:
            outcome = next(outcomes)
        except grpc.RpcError as exc:
            self.end_stream()  # its request thread waits on the queue: let it go
            raise call_error(call.rpc, exc) from None
        except StopIteration:
            self.end_stream()
            raise calls.stream_ended(call) from None
        except BaseException:
            # Interrupted waiting (KeyboardInterrupt): the call is given up, and the
            # controller must see it so (the stream cancelled), not answer it later.
            self.end_stream()
            raise
        return calls.result_of(call, number, outcome)

    def end_stream(self) -> None:
        """Cancels the stream of calls, if one is open (the next call opens another)."""
        if self._stream is not None:
            requests, outcomes = self._stream
            self._stream = None
            requests.put(None)
            outcomes.cancel()

    def send(self, call: calls.Call[ResultT], **options: Any) -> ResultT:
        """Sends ``call`` as a unary call, whatever else is pending (the end of the program)."""
        try:
            reply = self._methods[call](call.request, metadata=self.metadata, **options)
        except grpc.RpcError as exc:
            raise call_error(call.rpc, exc) from None
        return call.result(reply)


class Mobility:
    """Movement: arm, take off, go to, land; position and flight state."""

    def __init__(self, call: _Caller) -> None:
        self._call = call

    def arm(self) -> None:
        """Arms the motors."""
        self._call(calls.arm())

    def disarm(self) -> None:
        """Disarms the motors."""
        self._call(calls.disarm())

    def takeoff(self, altitude_m: float) -> None:
        """Starts climbing to ``altitude_m`` above home."""
        self._call(calls.takeoff(altitude_m))

    def goto(self, target: Position, relative_altitude_m: float | None = None) -> None:
        """Starts flying to ``target`` (at its relative altitude unless one is given)."""
        self._call(calls.goto(target, relative_altitude_m))

    def set_speed(self, speed_m_s: float) -> None:
        """Sets the cruise speed of later gotos."""
        self._call(calls.set_speed(speed_m_s))

    def hold(self) -> None:
        """Stops and holds position."""
        self._call(calls.hold())

    def land(self) -> None:
        """Lands where the vehicle is."""
        self._call(calls.land())

    def return_to_launch(self) -> None:
        """Flies home and lands."""
        self._call(calls.return_to_launch())

    def position(self) -> Position:
        """The vehicle's latest position."""
        return self._call(calls.position())

    def home(self) -> Position:
        """The home position."""
        return self._call(calls.home())

    def flight_state(self) -> FlightState:
        """Armed, in air, mode, battery, readiness."""
        return self._call(calls.flight_state())


class Camera:
    """The on-board camera."""

    def __init__(self, call: _Caller) -> None:
        self._call = call

    def set_resolution(self, width: int, height: int) -> tuple[int, int]:
        """Sets the picture size; returns the size in use."""
        return self._call(calls.set_resolution(width, height))

    def take_picture(self) -> Picture:
        """Takes a picture."""
        return self._call(calls.take_picture())


class Gimbal:
    """Where the camera points: a region of interest, until cleared."""

    def __init__(self, call: _Caller) -> None:
        self._call = call

    def set_roi_location(self, target: Position, relative_altitude_m: float | None = None) -> None:
        """Points the camera at ``target`` (at its relative altitude unless one is given)."""
        self._call(calls.set_roi_location(target, relative_altitude_m))

    def clear_roi(self) -> None:
        """Clears the region of interest."""
        self._call(calls.clear_roi())


class Clock:
    """Mission time: sleeps really only while the controller is the active master."""

    def __init__(self, call: _Caller) -> None:
        self._call = call

    def sleep(self, seconds: float) -> None:
        """Sleeps ``seconds`` of mission time (at once while replaying)."""
        self._call(calls.sleep(seconds))

    def now(self) -> float:
        """Mission time, Unix seconds; the same on every replica."""
        return self._call(calls.now())


def mission_token_metadata(token: str | None = None) -> tuple[tuple[str, str], ...]:
    """The metadata that carries the mission token (baton.rpc.mission): ``token``, else
    this program's from its environment, if it has one."""
    token = token or os.environ.get(MISSION_TOKEN_ENV)
    return ((MISSION_TOKEN_METADATA, token),) if token else ()


class Drone:
    """A drone, as seen through the local mission controller.

    ``channel``: one to use instead of a connection to ``address`` (``baton
    replay`` gives one that answers from a saved log, in-process). ``token``:
    the mission token, if not this program's ``BATON_MISSION_TOKEN``.
    """

    def __init__(
        self, address: str, channel: grpc.Channel | None = None, token: str | None = None
    ) -> None:
        self.address = address
        self._channel = sync_channel(address) if channel is None else channel
        self._call = _Caller(self._channel, mission_token_metadata(token))
        self.mobility = Mobility(self._call)
        self.camera = Camera(self._call)
        self.gimbal = Gimbal(self._call)
        self.clock = Clock(self._call)

    def close(self, error: str = "") -> None:
        """Tells the controller the mission has ended, then closes the channel."""
        try:
            self._call.send(calls.mission_done(error), timeout=calls.MISSION_DONE_TIMEOUT_S)
        except DroneCallError:
            pass  # the controller is gone: nothing left to flush to
        finally:
            self._call.end_stream()
            self._channel.close()

    def __enter__(self) -> Drone:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close(error=repr(exc) if exc is not None else "")


def connect(address: str) -> Drone:
    """A Drone through the controller at ``host:port``."""
    return Drone(address)
