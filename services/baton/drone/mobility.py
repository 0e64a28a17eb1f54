"""Mobility through MAVSDK 4.x: the drone service's backend for a real or sim autopilot.

One ``Mavsdk`` instance per vehicle (two vehicles with one system id on one
instance would merge). ``start()`` adds the connection and returns; a
background task waits for the autopilot, asks for the telemetry rates we read
(a real ArduPilot streams little until asked), and keeps the latest value of
each telemetry stream through MAVSDK subscriptions. Reads (GetPosition,
GetHome, GetFlightState) answer from that cache without touching MAVSDK, so
they stay fast while commands are pending. Commands go through MAVSDK's
``ActionAsync``, which runs each call in the loop's default executor; since a
handful of workers on 2 cores made reads wait behind commands (DESIGN.md),
the loop gets a larger default executor the first time a backend starts on it.
"""

from __future__ import annotations

import asyncio
import math
import weakref
from collections.abc import AsyncIterator, Awaitable, Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, TypeVar

import grpc

from baton import logs
from baton.rpc.errors import StatusError
from baton.v1 import drone_api_pb2 as api

T = TypeVar("T")

# Workers of the loop's default executor, which MAVSDK's asyncio API uses for
# every awaited call.
EXECUTOR_WORKERS = 32
_loops_with_executor: weakref.WeakSet[asyncio.AbstractEventLoop] = weakref.WeakSet()

_log = logs.get_logger("mavsdk")
_mavsdk_logs_captured = False


@dataclass(frozen=True)
class TelemetryRates:
    """Rates (Hz) asked of the autopilot on connect; 0 leaves one as it is."""

    position_hz: float = 20.0
    home_hz: float = 1.0
    in_air_hz: float = 5.0
    landed_state_hz: float = 5.0
    battery_hz: float = 1.0


def capture_mavsdk_logs() -> None:
    """Routes MAVSDK's own log lines (printed to stdout otherwise) into baton.logs."""
    global _mavsdk_logs_captured
    if _mavsdk_logs_captured:
        return
    import mavsdk

    def forward(level: Any, message: str, file: str | None, line: int) -> bool:
        if level >= mavsdk.LogLevel.WARN:
            _log.warning(message, mavsdk_level=level.name, source=f"{file}:{line}")
        else:
            _log.debug(message, mavsdk_level=level.name)
        return True  # handled: MAVSDK prints nothing

    mavsdk.log_subscribe(forward)
    _mavsdk_logs_captured = True


def _ensure_executor(loop: asyncio.AbstractEventLoop) -> None:
    if loop not in _loops_with_executor:
        loop.set_default_executor(
            ThreadPoolExecutor(max_workers=EXECUTOR_WORKERS, thread_name_prefix="mavsdk")
        )
        _loops_with_executor.add(loop)


def _require_finite(name: str, value: float) -> None:
    if not math.isfinite(value):
        raise StatusError(grpc.StatusCode.INVALID_ARGUMENT, f"{name} must be finite, got {value}")


def _require_positive(name: str, value: float) -> None:
    _require_finite(name, value)
    if value <= 0:
        raise StatusError(grpc.StatusCode.INVALID_ARGUMENT, f"{name} must be > 0, got {value}")


def _require_range(name: str, value: float, low: float, high: float) -> None:
    _require_finite(name, value)
    if not low <= value <= high:
        raise StatusError(
            grpc.StatusCode.INVALID_ARGUMENT, f"{name} must be in [{low}, {high}], got {value}"
        )


def _status_of_action_error(result_name: str) -> grpc.StatusCode:
    """The gRPC code for a MAVSDK ActionResult (by name)."""
    if result_name in ("NO_SYSTEM", "CONNECTION_ERROR", "TIMEOUT"):
        return grpc.StatusCode.UNAVAILABLE
    if result_name in (
        "BUSY",
        "COMMAND_DENIED",
        "COMMAND_DENIED_LANDED_STATE_UNKNOWN",
        "COMMAND_DENIED_NOT_LANDED",
    ):
        return grpc.StatusCode.FAILED_PRECONDITION
    if result_name == "INVALID_ARGUMENT":
        return grpc.StatusCode.INVALID_ARGUMENT
    return grpc.StatusCode.ABORTED


def _position(source: Any) -> api.Position:
    return api.Position(
        latitude_deg=source.latitude_deg,
        longitude_deg=source.longitude_deg,
        absolute_altitude_m=source.absolute_altitude_m,
        relative_altitude_m=source.relative_altitude_m,
    )


class MavsdkMobility:
    """The Mobility backend for one vehicle at a MAVLink URL (see ``MobilityBackend``)."""

    def __init__(
        self,
        url: str,
        *,
        rates: TelemetryRates | None = None,
        command_timeout_s: float = 10.0,
    ) -> None:
        self.url = url
        self.rates = rates or TelemetryRates()
        self.command_timeout_s = command_timeout_s
        self._mavsdk: Any = None
        self._action: Any = None
        self._telemetry: Any = None
        self._connected = False
        self._tasks: list[asyncio.Task[None]] = []
        # Latest value of each telemetry stream, by name; filled by subscriptions.
        self._latest: dict[str, Any] = {}
        self._log = logs.get_logger("drone.mobility", vehicle=url)

    # --- connection ------------------------------------------------------------------

    async def start(self) -> None:
        """Adds the connection and starts waiting for the autopilot in the background."""
        from mavsdk.asyncio import ComponentType, Configuration, Mavsdk, MavsdkConnectionError

        capture_mavsdk_logs()
        _ensure_executor(asyncio.get_running_loop())
        config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
        self._mavsdk = Mavsdk(config)
        try:
            await self._mavsdk.add_any_connection(self.url)
        except MavsdkConnectionError as exc:
            raise StatusError(
                grpc.StatusCode.INVALID_ARGUMENT, f"cannot open vehicle URL {self.url}: {exc}"
            ) from exc
        self._tasks.append(asyncio.create_task(self._attach(), name=f"mavsdk-attach {self.url}"))

    async def close(self) -> None:
        """Stops the background tasks and destroys the MAVSDK instance."""
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks.clear()
        self._connected = False
        if self._mavsdk is not None:
            self._mavsdk.destroy()
            self._mavsdk = None

    @property
    def connected(self) -> bool:
        """Whether an autopilot is connected now (heartbeats arriving)."""
        return self._connected

    async def wait_connected(self, timeout_s: float) -> bool:
        """Waits until an autopilot is connected; False on timeout (for tests and tools)."""
        deadline = asyncio.get_running_loop().time() + timeout_s
        while not self._connected:
            if asyncio.get_running_loop().time() >= deadline:
                return False
            await asyncio.sleep(0.02)
        return True

    async def _attach(self) -> None:
        from mavsdk.asyncio.plugins.action import ActionAsync
        from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

        # A negative timeout waits until an autopilot appears or we are cancelled.
        system = await self._mavsdk.first_autopilot(timeout_s=-1)
        if system is None:
            return  # destroyed while waiting
        self._action = ActionAsync(system)
        self._telemetry = TelemetryAsync(system)
        telemetry = self._telemetry
        for name, stream in (
            ("position", telemetry.subscribe_position),
            ("home", telemetry.subscribe_home),
            ("armed", telemetry.subscribe_armed),
            ("in_air", telemetry.subscribe_in_air),
            ("landed_state", telemetry.subscribe_landed_state),
            ("flight_mode", telemetry.subscribe_flight_mode),
            ("battery", telemetry.subscribe_battery),
            ("health", telemetry.subscribe_health),
        ):
            self._tasks.append(asyncio.create_task(self._keep_latest(name, stream())))
        self._tasks.append(asyncio.create_task(self._watch_connection(system)))
        self._connected = True
        self._log.info("vehicle connected", system_id=await system.get_system_id())
        await self._request_rates()

    async def _keep_latest(self, name: str, stream: AsyncIterator[Any]) -> None:
        async for value in stream:
            self._latest[name] = value

    async def _watch_connection(self, system: Any) -> None:
        async for connected in system.is_connected_state():
            if connected != self._connected:
                self._log.info("vehicle connection changed", connected=connected)
            self._connected = connected
            if connected:
                await self._request_rates()

    async def _request_rates(self) -> None:
        """Asks for the telemetry we read; an autopilot that refuses one still works."""
        telemetry, rates = self._telemetry, self.rates
        for name, setter, hz in (
            ("position", telemetry.set_rate_position, rates.position_hz),
            ("home", telemetry.set_rate_home, rates.home_hz),
            ("in_air", telemetry.set_rate_in_air, rates.in_air_hz),
            ("landed_state", telemetry.set_rate_landed_state, rates.landed_state_hz),
            ("battery", telemetry.set_rate_battery, rates.battery_hz),
        ):
            if hz <= 0:
                continue
            try:
                await setter(hz)
            except Exception as exc:  # MAVSDK's TelemetryError, or a lost link
                self._log.warning("telemetry rate refused", stream=name, hz=hz, error=str(exc))

    # --- helpers -----------------------------------------------------------------------

    def _require_connected(self) -> None:
        if not self._connected or self._action is None:
            raise StatusError(grpc.StatusCode.UNAVAILABLE, f"vehicle at {self.url} not connected")

    async def _command(self, what: str, call: Callable[[], Awaitable[T]]) -> T:
        """Runs one MAVSDK action, mapping its failure to a StatusError."""
        from mavsdk.plugins.action import ActionError

        self._require_connected()
        try:
            return await asyncio.wait_for(call(), self.command_timeout_s)
        except ActionError as exc:
            raise StatusError(
                _status_of_action_error(exc.result.name),
                f"vehicle at {self.url} refused {what}: {exc}",
            ) from exc
        except TimeoutError as exc:
            raise StatusError(
                grpc.StatusCode.UNAVAILABLE,
                f"vehicle at {self.url} did not answer {what} within {self.command_timeout_s} s",
            ) from exc

    def _cached(self, name: str) -> Any:
        self._require_connected()
        value = self._latest.get(name)
        if value is None:
            raise StatusError(
                grpc.StatusCode.UNAVAILABLE, f"vehicle at {self.url} has not sent its {name} yet"
            )
        return value

    # --- Mobility RPCs -------------------------------------------------------------------

    async def Arm(self, request: api.ArmRequest) -> api.ArmReply:
        """Arms the motors."""
        await self._command("arm", lambda: self._action.arm())
        return api.ArmReply()

    async def Disarm(self, request: api.DisarmRequest) -> api.DisarmReply:
        """Disarms the motors."""
        await self._command("disarm", lambda: self._action.disarm())
        return api.DisarmReply()

    async def Takeoff(self, request: api.TakeoffRequest) -> api.TakeoffReply:
        """Sets the takeoff altitude (MIS_TAKEOFF_ALT on PX4), then takes off."""
        _require_positive("altitude_m", request.altitude_m)
        await self._command(
            "set takeoff altitude", lambda: self._action.set_takeoff_altitude(request.altitude_m)
        )
        await self._command("takeoff", lambda: self._action.takeoff())
        return api.TakeoffReply()

    async def Goto(self, request: api.GotoRequest) -> api.GotoReply:
        """Flies to the location; altitude AMSL = home AMSL + relative altitude."""
        _require_range("latitude_deg", request.latitude_deg, -90.0, 90.0)
        _require_range("longitude_deg", request.longitude_deg, -180.0, 180.0)
        _require_positive("relative_altitude_m", request.relative_altitude_m)
        yaw = request.yaw_deg
        if not math.isnan(yaw):
            _require_finite("yaw_deg", yaw)
        home = self._cached("home")
        if not math.isfinite(home.absolute_altitude_m):
            raise StatusError(
                grpc.StatusCode.FAILED_PRECONDITION, f"vehicle at {self.url} has no home yet"
            )
        absolute = home.absolute_altitude_m + request.relative_altitude_m
        keep_yaw = math.nan if math.isnan(yaw) or yaw == 0.0 else yaw
        await self._command(
            "goto",
            lambda: self._action.goto_location(
                request.latitude_deg, request.longitude_deg, absolute, keep_yaw
            ),
        )
        return api.GotoReply()

    async def SetSpeed(self, request: api.SetSpeedRequest) -> api.SetSpeedReply:
        """Sets the cruise speed of later gotos."""
        _require_positive("speed_m_s", request.speed_m_s)
        await self._command("set speed", lambda: self._action.set_current_speed(request.speed_m_s))
        return api.SetSpeedReply()

    async def Hold(self, request: api.HoldRequest) -> api.HoldReply:
        """Holds the current position."""
        await self._command("hold", lambda: self._action.hold())
        return api.HoldReply()

    async def Land(self, request: api.LandRequest) -> api.LandReply:
        """Lands where the vehicle is."""
        await self._command("land", lambda: self._action.land())
        return api.LandReply()

    async def ReturnToLaunch(self, request: api.ReturnToLaunchRequest) -> api.ReturnToLaunchReply:
        """Flies home and lands."""
        await self._command("return to launch", lambda: self._action.return_to_launch())
        return api.ReturnToLaunchReply()

    async def GetPosition(self, request: api.GetPositionRequest) -> api.GetPositionReply:
        """The latest position, from the telemetry cache."""
        return api.GetPositionReply(position=_position(self._cached("position")))

    async def GetHome(self, request: api.GetHomeRequest) -> api.GetHomeReply:
        """The home position, from the telemetry cache."""
        return api.GetHomeReply(home=_position(self._cached("home")))

    async def GetFlightState(self, request: api.GetFlightStateRequest) -> api.GetFlightStateReply:
        """Armed, in air, mode, battery and readiness, from the telemetry cache."""
        self._require_connected()
        latest = self._latest
        battery = latest.get("battery")
        health = latest.get("health")
        mode = latest.get("flight_mode")
        landed = latest.get("landed_state")
        return api.GetFlightStateReply(
            armed=bool(latest.get("armed", False)),
            in_air=bool(latest.get("in_air", False)),
            flight_mode=mode.name if mode is not None else "UNKNOWN",
            battery_percent=battery.remaining_percent if battery is not None else math.nan,
            ready=bool(
                health is not None and health.is_global_position_ok and health.is_home_position_ok
            ),
            landed_state=landed.name if landed is not None else "UNKNOWN",
        )
