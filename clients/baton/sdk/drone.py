"""The ``Drone`` handle: mobility, camera and clock over the generated stubs."""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from types import TracebackType
from typing import Any, TypeVar

import grpc

from baton.rpc.channels import sync_channel
from baton.rpc.mission import MISSION_TOKEN_ENV, MISSION_TOKEN_METADATA
from baton.sdk.errors import ConcurrentCallError, DroneCallError
from baton.sdk.types import FlightState, Picture, Position
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_api_pb2_grpc, ring_pb2, ring_pb2_grpc

ReplyT = TypeVar("ReplyT")


class _Caller:
    """Makes one call at a time and turns gRPC errors into DroneCallError."""

    def __init__(self, metadata: tuple[tuple[str, str], ...] = ()) -> None:
        self._lock = threading.Lock()
        self.metadata = metadata  # the mission token (baton.rpc.mission), if given

    def __call__(self, rpc: str, method: Callable[..., ReplyT], request: Any) -> ReplyT:
        if not self._lock.acquire(blocking=False):
            raise ConcurrentCallError(
                f"{rpc} called while another drone call is pending: "
                "a mission program makes one call at a time, so that every replica replays it"
            )
        try:
            # No deadline: a PASSIVE controller holds the call until it may answer.
            return method(request, wait_for_ready=True, metadata=self.metadata)
        except grpc.RpcError as exc:
            code = exc.code() if isinstance(exc, grpc.Call) else grpc.StatusCode.UNKNOWN
            details = (exc.details() if isinstance(exc, grpc.Call) else str(exc)) or ""
            raise DroneCallError(rpc, code, details) from None
        finally:
            self._lock.release()


class Mobility:
    """Movement: arm, take off, go to, land; position and flight state."""

    def __init__(self, channel: grpc.Channel, call: _Caller) -> None:
        self._stub = drone_api_pb2_grpc.MobilityStub(channel)
        self._call = call

    def arm(self) -> None:
        """Arms the motors."""
        self._call("Mobility.Arm", self._stub.Arm, api.ArmRequest())

    def disarm(self) -> None:
        """Disarms the motors."""
        self._call("Mobility.Disarm", self._stub.Disarm, api.DisarmRequest())

    def takeoff(self, altitude_m: float) -> None:
        """Starts climbing to ``altitude_m`` above home."""
        self._call(
            "Mobility.Takeoff", self._stub.Takeoff, api.TakeoffRequest(altitude_m=altitude_m)
        )

    def goto(self, target: Position, relative_altitude_m: float | None = None) -> None:
        """Starts flying to ``target`` (at its relative altitude unless one is given)."""
        altitude = (
            target.relative_altitude_m if relative_altitude_m is None else relative_altitude_m
        )
        request = api.GotoRequest(
            latitude_deg=target.latitude_deg,
            longitude_deg=target.longitude_deg,
            relative_altitude_m=altitude,
        )
        self._call("Mobility.Goto", self._stub.Goto, request)

    def set_speed(self, speed_m_s: float) -> None:
        """Sets the cruise speed of later gotos."""
        self._call(
            "Mobility.SetSpeed", self._stub.SetSpeed, api.SetSpeedRequest(speed_m_s=speed_m_s)
        )

    def hold(self) -> None:
        """Stops and holds position."""
        self._call("Mobility.Hold", self._stub.Hold, api.HoldRequest())

    def land(self) -> None:
        """Lands where the vehicle is."""
        self._call("Mobility.Land", self._stub.Land, api.LandRequest())

    def return_to_launch(self) -> None:
        """Flies home and lands."""
        self._call(
            "Mobility.ReturnToLaunch", self._stub.ReturnToLaunch, api.ReturnToLaunchRequest()
        )

    def position(self) -> Position:
        """The vehicle's latest position."""
        reply = self._call("Mobility.GetPosition", self._stub.GetPosition, api.GetPositionRequest())
        return Position.from_proto(reply.position)

    def home(self) -> Position:
        """The home position."""
        reply = self._call("Mobility.GetHome", self._stub.GetHome, api.GetHomeRequest())
        return Position.from_proto(reply.home)

    def flight_state(self) -> FlightState:
        """Armed, in air, mode, battery, readiness."""
        reply = self._call(
            "Mobility.GetFlightState", self._stub.GetFlightState, api.GetFlightStateRequest()
        )
        return FlightState.from_proto(reply)


class Camera:
    """The on-board camera."""

    def __init__(self, channel: grpc.Channel, call: _Caller) -> None:
        self._stub = drone_api_pb2_grpc.CameraStub(channel)
        self._call = call

    def set_resolution(self, width: int, height: int) -> tuple[int, int]:
        """Sets the picture size; returns the size in use."""
        reply = self._call(
            "Camera.SetResolution",
            self._stub.SetResolution,
            api.SetResolutionRequest(width=width, height=height),
        )
        return reply.width, reply.height

    def take_picture(self) -> Picture:
        """Takes a picture."""
        reply = self._call("Camera.TakePicture", self._stub.TakePicture, api.TakePictureRequest())
        return Picture.from_proto(reply)


class Clock:
    """Mission time: sleeps really only while the controller is the active master."""

    def __init__(self, channel: grpc.Channel, call: _Caller) -> None:
        self._stub = drone_api_pb2_grpc.ClockStub(channel)
        self._call = call

    def sleep(self, seconds: float) -> None:
        """Sleeps ``seconds`` of mission time (at once while replaying)."""
        self._call("Clock.Sleep", self._stub.Sleep, api.SleepRequest(seconds=seconds))

    def now(self) -> float:
        """Mission time, Unix seconds; the same on every replica."""
        return self._call("Clock.Now", self._stub.Now, api.NowRequest()).unix_time_s


class Drone:
    """A drone, as seen through the local mission controller.

    ``channel``: one to use instead of a connection to ``address`` (``baton
    replay`` gives one that answers from a saved log, in-process).
    """

    def __init__(self, address: str, channel: grpc.Channel | None = None) -> None:
        self.address = address
        self._channel = sync_channel(address) if channel is None else channel
        token = os.environ.get(MISSION_TOKEN_ENV)
        call = _Caller(((MISSION_TOKEN_METADATA, token),) if token else ())
        self._metadata = call.metadata
        self.mobility = Mobility(self._channel, call)
        self.camera = Camera(self._channel, call)
        self.clock = Clock(self._channel, call)
        self._ring = ring_pb2_grpc.ControllerRingStub(self._channel)

    def close(self, error: str = "") -> None:
        """Tells the controller the mission has ended, then closes the channel."""
        try:
            self._ring.MissionDone(
                ring_pb2.MissionDoneRequest(failed=bool(error), error=error),
                timeout=10,
                metadata=self._metadata,
            )
        except grpc.RpcError:
            pass  # the controller is gone: nothing left to flush to
        finally:
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
