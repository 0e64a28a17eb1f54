"""Mobility through MAVSDK 4.x: the drone service's backend for a real or sim autopilot.

One ``Mavsdk`` instance per vehicle (two vehicles with one system id on one
instance would merge). ``start()`` adds the connection and returns; a
background task waits for the autopilot and keeps the latest value of each
telemetry stream through MAVSDK subscriptions, with the time it arrived.
Reads (GetPosition, GetHome, GetFlightState) answer from that cache without
touching MAVSDK, so they stay fast while commands are pending, and refuse
with UNAVAILABLE while the link is out (``vehicle_state.LinkMonitor``: no
heartbeat, or a position older than its bound), never serving a dead
autopilot's last position as fresh. A watchdog asks the autopilot for the
streams whenever heartbeats arrive without position telemetry: a real
ArduPilot streams nothing until asked and forgets it on reboot.

Commands go through MAVSDK's ``ActionAsync``, which runs each call in the
loop's default executor; since a handful of workers on 2 cores made reads wait
behind commands (docs/design.md), the loop gets a larger default executor the
first time a backend starts on it (``MavsdkRuntime``, shared by the process's
backends and given to each). What MAVSDK's Action does not do right on
ArduPilot is done beside it with raw MAVLink commands (``MavlinkDirect``):
GUIDED before arming, the cruise speed re-applied after every goto.

The Gimbal service is answered here too (the gimbal is reached over the same
link): a region of interest through MAVSDK's Gimbal plugin, addressed to all
gimbal managers (gimbal id 0: no gimbal discovery needed; the autopilot is the
manager of a gimbal it drives, and points the vehicle's yaw where it has none),
and cleared with a raw ``MAV_CMD_DO_SET_ROI_NONE``, which that plugin lacks.
"""

from __future__ import annotations

import asyncio
import json
import math
import time
import weakref
from collections.abc import AsyncIterator, Awaitable, Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import grpc
from pymavlink.dialects.v20 import common as mavlink

from baton import logs
from baton.drone.gcs import GcsLink
from baton.drone.mavlink_relay import MavlinkRelay
from baton.drone.safety import (
    AutopilotParam,
    VehicleLimits,
    fence_params,
    gcs_failsafe_params,
    limit_params,
    vehicle_limits,
)
from baton.drone.tlog import TlogWriter, tlog_path
from baton.drone.vehicle_state import (
    ARDUPILOT_COMMAND_MODE,
    PREARM_TEXT_VALID_S,
    Health,
    Heartbeat,
    LinkMonitor,
    Readiness,
    flight_state_missing,
    is_prearm_text,
    readiness,
)
from baton.rpc.errors import StatusError
from baton.sdk.fence import Fence
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2

T = TypeVar("T")

# How long a parameter read or write may take before the autopilot counts as
# lacking it (MAVSDK's own parameter timeouts are longer and retried).
PARAM_TIMEOUT_S = 3.0
# ArduPilot's EKF_STATUS_REPORT (not in the common dialect).
EKF_STATUS_REPORT_ID = 193

# An autopilot that refuses to arm while it reports itself ready (an arming
# check failed between ArduPilot's 1 Hz pre-arm reports: seen on a loaded
# machine) is asked again every ARM_RETRY_S while it stays ready, for at most
# ARM_SETTLE_S; a refused arm did nothing, so asking again cannot arm twice.
ARM_SETTLE_S = 5.0
ARM_RETRY_S = 0.5

# Workers of the loop's default executor, which MAVSDK's asyncio API uses for
# every awaited call.
EXECUTOR_WORKERS = 32

_log = logs.get_logger("mavsdk")


@dataclass(frozen=True)
class TelemetryRates:
    """Rates (Hz) asked of the autopilot on connect; 0 leaves one as it is."""

    position_hz: float = 20.0
    home_hz: float = 1.0
    in_air_hz: float = 5.0
    landed_state_hz: float = 5.0
    battery_hz: float = 1.0
    health_hz: float = 2.0  # SYS_STATUS: GPS health and the pre-arm bit (readiness)


class MavsdkRuntime:
    """What the MAVSDK backends of one process share, set up once by the first to start.

    MAVSDK's log lines go to one callback per process (its C library's), which
    routes them into baton.logs instead of stdout. Its asyncio API runs every
    blocking call with ``run_in_executor(None, ...)``, the loop's default
    executor, which is therefore the only one it can be given: each event loop
    a backend starts on gets, once, a default executor of ``workers`` threads
    owned here (``asyncio.run`` shuts it down with the loop).
    """

    def __init__(self, workers: int = EXECUTOR_WORKERS) -> None:
        self.workers = workers
        self._logs_captured = False
        self._executors: weakref.WeakKeyDictionary[
            asyncio.AbstractEventLoop, ThreadPoolExecutor
        ] = weakref.WeakKeyDictionary()

    def prepare(self, loop: asyncio.AbstractEventLoop) -> None:
        """Captures MAVSDK's logs and gives ``loop`` its executor, each the first time only."""
        self.capture_logs()
        if loop not in self._executors:
            executor = ThreadPoolExecutor(max_workers=self.workers, thread_name_prefix="mavsdk")
            loop.set_default_executor(executor)
            self._executors[loop] = executor

    def capture_logs(self) -> None:
        """Routes MAVSDK's own log lines (printed to stdout otherwise) into baton.logs."""
        if self._logs_captured:
            return
        import mavsdk

        def forward(level: Any, message: str, file: str | None, line: int) -> bool:
            if level >= mavsdk.LogLevel.WARN:
                _log.warning(message, mavsdk_level=level.name, source=f"{file}:{line}")
            else:
                _log.debug(message, mavsdk_level=level.name)
            return True  # handled: MAVSDK prints nothing

        mavsdk.log_subscribe(forward)
        self._logs_captured = True


# The process's one runtime (MAVSDK's log callback is process-wide): every
# MavsdkMobility shares it unless it is given another.
PROCESS_RUNTIME = MavsdkRuntime()


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
    if result_name == "NO_SYSTEM":
        return grpc.StatusCode.UNAVAILABLE  # nothing was sent: the request may be sent again
    if result_name in ("CONNECTION_ERROR", "TIMEOUT"):
        # Sent, but no acknowledgement: the vehicle may have acted. Not
        # UNAVAILABLE, which the drone service treats as "nothing executed".
        return grpc.StatusCode.DEADLINE_EXCEEDED
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

    # How often the watchdog looks at the link.
    WATCH_PERIOD_S = 0.2
    # While an outage lasts, it is logged again this often.
    OUTAGE_LOG_PERIOD_S = 5.0

    def __init__(
        self,
        url: str,
        *,
        rates: TelemetryRates | None = None,
        command_timeout_s: float = 10.0,
        position_max_age_s: float = 1.0,
        heartbeat_timeout_s: float = 3.0,
        signing_key: bytes | None = None,
        tlog_dir: Path | None = None,
        gcs: GcsLink | None = None,
        runtime: MavsdkRuntime = PROCESS_RUNTIME,
        gcs_failsafe_timeout_s: float = 0.0,
        fence: Fence | None = None,
    ) -> None:
        self.url = url
        # The mission's fence (drone/fence.py), uploaded at connect, after a reboot and
        # before arming; ``_fence_held``: the autopilot accepted it since it was last
        # (re)connected.
        self.fence = fence
        self._fence_held = False
        self._fence_lock = asyncio.Lock()  # one upload at a time (MAVSDK answers BUSY)
        self._geofence: Any = None
        # The autopilot's own GCS failsafe (safety.gcs_failsafe_params); 0: left alone.
        self.gcs_failsafe_timeout_s = gcs_failsafe_timeout_s
        self._param: Any = None
        self._gcs_sysid = 245
        # The bounds the autopilot said at its last connect (None: not read yet).
        self._limits: VehicleLimits | None = None
        self._runtime = runtime
        # Ground stations watching live (drone/gcs.py), fed by the relay.
        self.gcs = gcs
        # With a key, a telemetry log or ground stations, MAVSDK talks to the autopilot
        # through the relay.
        self._relay: MavlinkRelay | None = None
        if signing_key is not None or tlog_dir is not None or gcs is not None:
            tlog = TlogWriter(tlog_path(tlog_dir)) if tlog_dir is not None else None
            self._relay = MavlinkRelay(url, signing_key, tlog, gcs)
        self.rates = rates or TelemetryRates()
        self.command_timeout_s = command_timeout_s
        self.monitor = LinkMonitor(
            heartbeat_timeout_s=heartbeat_timeout_s, position_max_age_s=position_max_age_s
        )
        self._mavsdk: Any = None
        self._action: Any = None
        self._telemetry: Any = None
        self._direct: Any = None
        self._gimbal: Any = None
        # The region of interest the autopilot accepted last (None: none, or cleared).
        self._roi: api.Position | None = None
        self._system_id = 0
        self._tasks: list[asyncio.Task[None]] = []
        # Latest value of each telemetry stream, by name; filled by subscriptions.
        self._latest: dict[str, Any] = {}
        self._heartbeat: Heartbeat | None = None
        self._prearm: tuple[str, float] | None = None  # latest "PreArm: ..." and when
        # The cruise speed the mission asked for; ArduCopter resets it to
        # WPNAV_SPEED at every guided reposition, so it is sent after each goto.
        self._speed_m_s: float | None = None
        self._outage_logged_at = 0.0
        self._log = logs.get_logger("drone.mobility", vehicle=url)

    # --- connection ------------------------------------------------------------------

    async def start(self) -> None:
        """Adds the connection and starts waiting for the autopilot in the background."""
        from mavsdk.asyncio import ComponentType, Configuration, Mavsdk, MavsdkConnectionError

        self._runtime.prepare(asyncio.get_running_loop())
        config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
        self._gcs_sysid = config.system_id
        self._mavsdk = Mavsdk(config)
        url = self.url if self._relay is None else await self._relay.start()
        try:
            await self._mavsdk.add_any_connection(url)
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
        self._action = None
        if self._mavsdk is not None:
            self._mavsdk.destroy()
            self._mavsdk = None
        if self._relay is not None:
            await self._relay.close()

    @property
    def connected(self) -> bool:
        """Whether the autopilot is there now: heartbeats arriving, position fresh."""
        return self._action is not None and self.monitor.healthy(time.monotonic())

    def link(self) -> drone_pb2.VehicleLink:
        """The link to the autopilot now, for GetStatus."""
        link = self.monitor.snapshot(self._observe_link())
        relay = self._relay
        if relay is not None:
            link.signing, link.refused_frames = relay.signer is not None, relay.refused
            link.last_refusal = relay.last_refusal
            if link.problem and relay.refused:
                link.problem += (
                    f"; {relay.refused} frames from the autopilot refused by MAVLink signing "
                    f"({relay.last_refusal}): does it hold the drone's key?"
                )
        return link

    def ground_velocity(self) -> tuple[float, float] | None:
        """North and east m/s from the autopilot's GLOBAL_POSITION_INT (MAVSDK's
        velocity_ned); None while the link is out or none arrived yet."""
        velocity = self._latest.get("velocity")
        if velocity is None or not self.connected:
            return None
        north, east = velocity.north_m_s, velocity.east_m_s
        return (north, east) if math.isfinite(north) and math.isfinite(east) else None

    async def _attach(self) -> None:
        from mavsdk.asyncio.plugins.action import ActionAsync
        from mavsdk.asyncio.plugins.geofence import GeofenceAsync
        from mavsdk.asyncio.plugins.gimbal import GimbalAsync
        from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync
        from mavsdk.asyncio.plugins.param import ParamAsync
        from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

        # A negative timeout waits until an autopilot appears or we are cancelled.
        system = await self._mavsdk.first_autopilot(timeout_s=-1)
        if system is None:
            return  # destroyed while waiting
        self._system_id = await system.get_system_id()
        self._telemetry = telemetry = TelemetryAsync(system)
        self._direct = MavlinkDirectAsync(system)
        self._gimbal = GimbalAsync(system)
        self._param = ParamAsync(system)
        self._geofence = GeofenceAsync(system)
        for name, stream in (
            ("position", telemetry.subscribe_position),
            ("velocity", telemetry.subscribe_velocity_ned),
            ("home", telemetry.subscribe_home),
            ("armed", telemetry.subscribe_armed),
            ("in_air", telemetry.subscribe_in_air),
            ("landed_state", telemetry.subscribe_landed_state),
            ("flight_mode", telemetry.subscribe_flight_mode),
            ("battery", telemetry.subscribe_battery),
        ):
            self._tasks.append(asyncio.create_task(self._keep_latest(name, stream())))
        self._tasks.append(asyncio.create_task(self._keep_heartbeat()))
        self._tasks.append(asyncio.create_task(self._keep_sys_status()))
        self._tasks.append(asyncio.create_task(self._keep_ekf_status()))
        self._tasks.append(asyncio.create_task(self._keep_status_text()))
        self._tasks.append(asyncio.create_task(self._watch()))
        self._action = ActionAsync(system)
        self._log.info("autopilot found", system_id=self._system_id)

    async def _keep_latest(self, name: str, stream: AsyncIterator[Any]) -> None:
        async for value in stream:
            self._latest[name] = value
            if name == "position":
                self.monitor.position(time.monotonic())

    async def _keep_heartbeat(self) -> None:
        """Heartbeats of the autopilot (not of other ground stations): liveness and mode."""
        async for message in self._direct.subscribe_message("HEARTBEAT"):
            if message.system_id != self._system_id:
                continue
            fields = json.loads(message.fields_json)
            if fields.get("autopilot") == mavlink.MAV_AUTOPILOT_INVALID:
                continue  # a ground station, a camera: not the autopilot
            heartbeat = Heartbeat(
                autopilot=fields["autopilot"],
                vehicle_type=fields["type"],
                base_mode=fields["base_mode"],
                custom_mode=fields["custom_mode"],
            )
            if self._heartbeat is None or heartbeat.custom_mode != self._heartbeat.custom_mode:
                self._log.info(
                    "autopilot mode",
                    autopilot=heartbeat.autopilot_name(),
                    mode=heartbeat.mode_name(),
                )
            self._heartbeat = heartbeat
            self.monitor.heard(time.monotonic())

    async def _keep_sys_status(self) -> None:
        """The autopilot's own SYS_STATUS, raw: the sensor and pre-arm bits readiness reads."""
        async for message in self._direct.subscribe_message("SYS_STATUS"):
            if message.system_id == self._system_id:
                self._latest["sys_status"] = json.loads(message.fields_json)
                self.monitor.status(time.monotonic())

    async def _keep_ekf_status(self) -> None:
        """ArduPilot's EKF_STATUS_REPORT flags: whether its estimator uses GPS yet."""
        async for message in self._direct.subscribe_message("EKF_STATUS_REPORT"):
            if message.system_id == self._system_id:
                self._latest["ekf_flags"] = int(json.loads(message.fields_json)["flags"])

    async def _keep_status_text(self) -> None:
        """The autopilot's STATUSTEXT into the log; "PreArm: ..." kept as the not-ready reason."""
        async for status in self._telemetry.subscribe_status_text():
            text = status.text
            severity = status.type.name
            if severity in ("INFO", "DEBUG", "NOTICE"):
                self._log.info("autopilot says", text=text, severity=severity)
            else:
                self._log.warning("autopilot says", text=text, severity=severity)
            if is_prearm_text(text):
                self._prearm = (text, time.monotonic())

    def _observe_link(self) -> float:
        """Notes (and logs) an outage starting or ending now; returns the time it looked."""
        now = time.monotonic()
        outage_since = self.monitor.outage_since
        change = self.monitor.update(now)
        if change == "outage":
            self._log.warning("vehicle link lost", problem=self.monitor.problem(now))
            self._outage_logged_at = now
            # What the autopilot said before is no longer known: a rebooted one
            # has no estimate and is not armable, whatever its last SYS_STATUS
            # said. Reads wait for fresh values (seen: ready and a 0,0 position
            # right after a SITL restart).
            self._latest.clear()
            self._prearm = None
            self._fence_held = False  # a rebooted autopilot may have lost it
        elif change == "recovered" and outage_since is not None:
            self._log.info("vehicle link back", outage_s=round(now - outage_since, 2))
        return now

    async def _watch(self) -> None:
        """Watches the link: logs outages, (re)requests streams when they do not come."""
        while True:
            now = self._observe_link()
            since = self.monitor.outage_since
            if since is not None and now - self._outage_logged_at >= self.OUTAGE_LOG_PERIOD_S:
                self._log.warning(
                    "vehicle link still down",
                    problem=self.monitor.problem(now),
                    outage_s=round(now - since, 1),
                )
                self._outage_logged_at = now
            if self.monitor.wants_streams(now):
                self.monitor.streams_requested(now)
                await self._request_rates()
            if self.monitor.wants_set_up(now):
                self.monitor.setting_up()
                # In the background: an autopilot without the parameters answers
                # nothing (timeouts).
                self._tasks.append(
                    asyncio.create_task(self._set_gcs_failsafe(), name="gcs-failsafe params")
                )
                self._tasks.append(
                    asyncio.create_task(self._read_limits(), name="autopilot limits")
                )
                if self.fence is not None and not self._fence_held:
                    self._tasks.append(
                        asyncio.create_task(self._fence_at_connect(), name="fence upload")
                    )
            await asyncio.sleep(self.WATCH_PERIOD_S)

    async def _request_rates(self) -> None:
        """Asks for the telemetry we read; an autopilot that refuses one still works."""
        telemetry, rates = self._telemetry, self.rates
        self._log.info("requesting telemetry streams", request=self.monitor.stream_requests)
        for name, setter, hz in (
            ("position", telemetry.set_rate_position, rates.position_hz),
            ("home", telemetry.set_rate_home, rates.home_hz),
            ("in_air", telemetry.set_rate_in_air, rates.in_air_hz),
            ("landed_state", telemetry.set_rate_landed_state, rates.landed_state_hz),
            ("battery", telemetry.set_rate_battery, rates.battery_hz),
            ("health", telemetry.set_rate_health, rates.health_hz),
        ):
            if hz <= 0:
                continue
            try:
                await setter(hz)
            except Exception as exc:  # MAVSDK's TelemetryError, or a lost link
                self._log.warning("telemetry rate refused", stream=name, hz=hz, error=str(exc))
        if self._heartbeat is not None and self._heartbeat.is_ardupilot and rates.health_hz > 0:
            try:  # MAVSDK has no setter for it; readiness reads it on ArduPilot
                await self._raw_command(
                    "EKF_STATUS_REPORT rate",
                    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                    EKF_STATUS_REPORT_ID,
                    1e6 / rates.health_hz,
                )
            except StatusError as exc:
                self._log.warning("telemetry rate refused", stream="ekf_status", error=str(exc))

    async def _set_gcs_failsafe(self) -> None:
        """Sets the autopilot's own GCS failsafe (``safety.gcs_failsafe_params``)."""
        heartbeat = self._heartbeat
        ardupilot = heartbeat is not None and heartbeat.is_ardupilot
        params = gcs_failsafe_params(ardupilot, self.gcs_failsafe_timeout_s, self._gcs_sysid)
        await self._set_params("autopilot GCS failsafe", params)

    def autopilot_limits(self) -> VehicleLimits | None:
        """The bounds the autopilot said at its last connect (``safety.vehicle_limits``)."""
        return self._limits

    async def _read_limits(self) -> None:
        """Reads the parameters that say the autopilot's bounds (``safety.limit_params``);
        one it does not answer within PARAM_TIMEOUT_S says no bound (logged)."""
        heartbeat = self._heartbeat
        ardupilot = heartbeat is not None and heartbeat.is_ardupilot
        values: dict[str, float] = {}
        own_ceiling = self.fence is not None and math.isfinite(self.fence.ceiling_m)
        for p in limit_params(ardupilot, own_ceiling=own_ceiling):
            get = self._param.get_param_int if p.integer else self._param.get_param_float
            try:
                values[p.name] = float(await asyncio.wait_for(get(p.name), PARAM_TIMEOUT_S))
            except Exception as exc:  # ParamError, a timeout: the autopilot lacks it
                self._log.info(
                    "autopilot bound not read: the autopilot does not have the parameter",
                    param=p.name,
                    error=f"{type(exc).__name__}: {exc}",
                )
        self._limits = vehicle_limits(ardupilot, values)
        self._log.info("autopilot bounds read", params=values, limits=str(self._limits))

    async def _set_params(self, what: str, params: list[AutopilotParam]) -> None:
        """Sets ``params`` in order where the autopilot has them: each read first, and the
        rest left alone (logged) from the first whose read gets no answer (the embedded
        sim vehicle knows only MIS_TAKEOFF_ALT and its link-loss parameters)."""
        done = []
        for p in params:
            get = self._param.get_param_int if p.integer else self._param.get_param_float
            put = self._param.set_param_int if p.integer else self._param.set_param_float
            value = int(p.value) if p.integer else float(p.value)
            try:
                held = await asyncio.wait_for(get(p.name), PARAM_TIMEOUT_S)
                if p.bits:  # set these bits, keep the autopilot's others
                    value = int(held) | int(p.value)
                await asyncio.wait_for(put(p.name, value), PARAM_TIMEOUT_S)
            except Exception as exc:  # ParamError, a timeout: the autopilot lacks it
                self._log.warning(
                    f"{what} not set: the autopilot does not take the parameter",
                    param=p.name,
                    error=f"{type(exc).__name__}: {exc}",
                )
                return
            done.append(f"{p.name}={value}")
        if done:
            self._log.info(f"{what} set", params=done)

    async def _fence_at_connect(self) -> None:
        """Uploads the fence at connect (a drone restarted mid-flight re-applies it); a
        failure is logged, and the next Arm tries again and refuses without it."""
        try:
            await self.upload_fence()
        except StatusError as err:
            self._log.warning("fence not uploaded at connect", reason=err.message)

    async def upload_fence(self) -> None:
        """Uploads the mission's fence through MAVSDK's Geofence plugin (the MAVLink
        mission protocol, MAV_MISSION_TYPE_FENCE): its polygons and circles; the
        ceiling is the drone's own check (the plugin carries no altitude)."""
        async with self._fence_lock:
            if not self._fence_held:  # the one before may have done it meanwhile
                await self._upload_fence()

    async def _upload_fence(self) -> None:
        from mavsdk.plugins.geofence import (
            Circle,
            FenceType,
            GeofenceData,
            GeofenceError,
            Point,
            Polygon,
        )

        fence = self.fence
        if fence is None or self._geofence is None:
            return

        def kind(inclusion: bool) -> Any:
            return FenceType.INCLUSION if inclusion else FenceType.EXCLUSION

        data = GeofenceData(
            polygons=[
                Polygon([Point(lat, lon) for lat, lon in p.vertices], kind(p.inclusion))
                for p in fence.polygons
            ],
            circles=[
                Circle(Point(c.latitude_deg, c.longitude_deg), c.radius_m, kind(c.inclusion))
                for c in fence.circles
            ],
        )
        try:
            await asyncio.wait_for(self._geofence.upload_geofence(data), self.command_timeout_s)
        except (GeofenceError, TimeoutError) as exc:
            raise StatusError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"vehicle at {self.url} did not take the mission's fence "
                f"({len(fence.polygons)} polygons, {len(fence.circles)} circles): "
                f"{exc or type(exc).__name__}",
            ) from exc
        self._fence_held = True
        self._log.info("fence uploaded", polygons=len(fence.polygons), circles=len(fence.circles))
        heartbeat = self._heartbeat
        params = fence_params(heartbeat is not None and heartbeat.is_ardupilot, fence)
        self._tasks.append(
            asyncio.create_task(self._set_params("autopilot fence", params), name="fence params")
        )

    # --- helpers -----------------------------------------------------------------------

    def _require_connected(self) -> None:
        if self._action is None:
            raise StatusError(
                grpc.StatusCode.UNAVAILABLE, f"vehicle at {self.url}: no autopilot found yet"
            )
        problem = self.monitor.problem(self._observe_link())
        if problem:
            raise StatusError(
                grpc.StatusCode.UNAVAILABLE, f"vehicle at {self.url} not connected: {problem}"
            )

    async def _command(self, what: str, call: Callable[[], Awaitable[T]]) -> T:
        """Runs one MAVSDK action (or gimbal command), mapping its failure to a StatusError."""
        from mavsdk.plugins.action import ActionError
        from mavsdk.plugins.gimbal import GimbalError

        self._require_connected()
        try:
            return await asyncio.wait_for(call(), self.command_timeout_s)
        except (ActionError, GimbalError) as exc:
            raise StatusError(
                _status_of_action_error(exc.result.name),
                f"vehicle at {self.url} refused {what}: {exc}",
            ) from exc
        except TimeoutError as exc:
            raise StatusError(
                grpc.StatusCode.DEADLINE_EXCEEDED,  # sent: it may have acted
                f"vehicle at {self.url} did not answer {what} within {self.command_timeout_s} s",
            ) from exc

    async def _raw_command(self, what: str, command: int, *params: float) -> None:
        """Sends COMMAND_LONG to the autopilot and waits for an accepting COMMAND_ACK."""
        from mavsdk.plugins.mavlink_direct import MavlinkDirectError, MavlinkMessage

        fields: dict[str, Any] = {
            "target_system": self._system_id,
            "target_component": mavlink.MAV_COMP_ID_AUTOPILOT1,
            "command": command,
            "confirmation": 0,
        }
        for index in range(7):
            fields[f"param{index + 1}"] = params[index] if index < len(params) else 0.0
        message = MavlinkMessage(
            message_name="COMMAND_LONG",
            target_system_id=self._system_id,
            target_component_id=mavlink.MAV_COMP_ID_AUTOPILOT1,
            fields_json=json.dumps(fields),
        )
        try:
            ack = await asyncio.wait_for(self._direct.send_command(message), self.command_timeout_s)
        except (MavlinkDirectError, TimeoutError) as exc:
            raise StatusError(
                grpc.StatusCode.DEADLINE_EXCEEDED,  # sent: it may have acted
                f"vehicle at {self.url} did not acknowledge {what}: {exc}",
            ) from exc
        result = json.loads(ack.fields_json or "{}").get("result")
        if result != mavlink.MAV_RESULT_ACCEPTED:
            entry = mavlink.enums["MAV_RESULT"].get(result) if result is not None else None
            raise StatusError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"vehicle at {self.url} refused {what}: {entry.name if entry else result}",
            )

    async def _enter_command_mode(self) -> None:
        """Puts ArduPilot in GUIDED, where it arms, takes off and flies to a location.

        After a landing ArduCopter sits in LAND; MAVSDK's arm would switch it
        to "Hold", which is BRAKE on a copter, where it refuses to arm. PX4
        and the sim vehicle need nothing: MAVSDK picks their modes.
        """
        heartbeat = self._heartbeat
        if heartbeat is None or not heartbeat.is_ardupilot:
            return
        if heartbeat.mode_name() == ARDUPILOT_COMMAND_MODE:
            return
        number = heartbeat.custom_mode_number(ARDUPILOT_COMMAND_MODE)
        if number is None:
            return  # a vehicle type without GUIDED: leave the mode to MAVSDK
        await self._raw_command(
            f"mode {ARDUPILOT_COMMAND_MODE}",
            mavlink.MAV_CMD_DO_SET_MODE,
            mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
            number,
        )

    def _cached(self, name: str) -> Any:
        self._require_connected()
        value = self._latest.get(name)
        if value is None:
            raise StatusError(
                grpc.StatusCode.UNAVAILABLE, f"vehicle at {self.url} has not sent its {name} yet"
            )
        return value

    def _readiness(self) -> Readiness:
        now = time.monotonic()
        prearm = self._prearm
        text = prearm[0] if prearm and now - prearm[1] <= PREARM_TEXT_VALID_S else None
        return readiness(self._health(), bool(self._latest.get("armed")), text)

    def _health(self) -> Health | None:
        """Health from this autopilot's latest SYS_STATUS; None before one arrived."""
        fields = self._latest.get("sys_status")
        if fields is None:
            return None
        ekf = self._latest.get("ekf_flags")
        return Health.from_messages(fields, home_known="home" in self._latest, ekf_flags=ekf)

    # --- Mobility RPCs -------------------------------------------------------------------

    async def Arm(self, request: api.ArmRequest) -> api.ArmReply:
        """Arms the motors (in GUIDED on ArduPilot), the mission's fence uploaded first; a
        refusal says why the vehicle is not ready."""
        self._require_connected()
        if self.fence is not None and not self._fence_held:
            await self.upload_fence()  # never armed without its fence
        started = time.monotonic()
        while True:
            try:
                await self._enter_command_mode()
                await self._command("arm", lambda: self._action.arm())
                return api.ArmReply()
            except StatusError as err:
                state = self._readiness()
                refused = err.code in (grpc.StatusCode.ABORTED, grpc.StatusCode.FAILED_PRECONDITION)
                prearm = self._prearm  # what it said since this Arm began
                said = prearm[0] if prearm and prearm[1] >= started - 1.0 else None
                if refused and state.ready and time.monotonic() - started < ARM_SETTLE_S:
                    self._log.warning(
                        "arm refused while the vehicle reports ready; asking again",
                        reason=err.message,
                        autopilot_says=said,
                    )
                    await asyncio.sleep(ARM_RETRY_S)
                    continue
                why = state.reason or (f"it says {said!r}" if refused and said else "")
                if why:
                    raise StatusError(err.code, f"{err.message}; not ready: {why}") from err
                raise

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
        """Flies to the location at the cruise speed; altitude AMSL = home AMSL + relative."""
        for name in ("latitude_deg", "longitude_deg"):
            if not request.HasField(name):
                raise StatusError(
                    grpc.StatusCode.INVALID_ARGUMENT,
                    f"Goto: {name} is missing; a target needs both latitude_deg and "
                    "longitude_deg (without them it was flown to 0°N 0°E)",
                )
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
        speed = self._speed_m_s
        if speed is not None:
            # The goto is accepted and flying: a refused speed must not make
            # it look failed (a retry would fly it again), so it is logged.
            try:
                await self._command("set speed", lambda: self._action.set_current_speed(speed))
            except StatusError as err:
                self._log.warning("cruise speed not applied after goto", reason=err.message)
        return api.GotoReply()

    def restore_speed(self, speed_m_s: float) -> None:
        """The cruise speed the mission set before the drone restarted: re-applied after
        every goto from now on, as it was (``MobilityBackend.restore_speed``)."""
        self._speed_m_s = speed_m_s

    async def SetSpeed(self, request: api.SetSpeedRequest) -> api.SetSpeedReply:
        """Sets the cruise speed of this flight leg (if flying) and of every later goto.

        On the ground it is only kept: ArduCopter refuses DO_CHANGE_SPEED
        before takeoff, and resets the speed at each reposition anyway, so
        ``Goto`` sends it after every reposition.
        """
        _require_positive("speed_m_s", request.speed_m_s)
        self._require_connected()
        if self._latest.get("in_air"):
            await self._command(
                "set speed", lambda: self._action.set_current_speed(request.speed_m_s)
            )
        self._speed_m_s = request.speed_m_s
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
        """The latest position, from the telemetry cache.

        UNAVAILABLE if stale, or while the estimator has no global position
        (ArduPilot sends latitude and longitude 0 until its EKF has an origin).
        """
        position = self._cached("position")
        health = self._health()
        unset = position.latitude_deg == 0 and position.longitude_deg == 0
        if health is None or not health.is_global_position_ok or unset:
            raise StatusError(
                grpc.StatusCode.UNAVAILABLE,
                f"vehicle at {self.url} has no global position yet: "
                f"{self._readiness().reason or 'its estimator does not use GPS'}",
            )
        return api.GetPositionReply(position=_position(position))

    async def GetHome(self, request: api.GetHomeRequest) -> api.GetHomeReply:
        """The home position, from the telemetry cache (UNAVAILABLE if the link is out)."""
        return api.GetHomeReply(home=_position(self._cached("home")))

    async def GetFlightState(self, request: api.GetFlightStateRequest) -> api.GetFlightStateReply:
        """Armed, in air, modes, battery, readiness and why not, from the telemetry cache;
        UNAVAILABLE until the autopilot has said whether it is armed and in the air
        (``flight_state_missing``)."""
        self._require_connected()
        latest = self._latest
        missing = flight_state_missing(latest)
        if missing is not None:
            raise StatusError(
                grpc.StatusCode.UNAVAILABLE,
                f"vehicle at {self.url} has not sent its {missing} yet: its flight state "
                "is not known",
            )
        battery = latest.get("battery")
        mode = latest.get("flight_mode")
        landed = latest.get("landed_state")
        heartbeat = self._heartbeat
        ready = self._readiness()
        return api.GetFlightStateReply(
            armed=bool(latest.get("armed", False)),
            in_air=bool(latest.get("in_air", False)),
            flight_mode=mode.name if mode is not None else "UNKNOWN",
            battery_percent=battery.remaining_percent if battery is not None else math.nan,
            ready=ready.ready,
            landed_state=landed.name if landed is not None else "UNKNOWN",
            armable=ready.armable,
            not_ready_reason=ready.reason,
            autopilot_mode=heartbeat.mode_name() if heartbeat else "UNKNOWN",
            autopilot=heartbeat.autopilot_name() if heartbeat else "UNKNOWN",
        )

    # --- Gimbal RPCs ---------------------------------------------------------------------

    def looking_at(self) -> api.Position | None:
        """The region of interest the autopilot accepted last; None if none is set."""
        return self._roi

    async def SetRoiLocation(self, request: api.SetRoiLocationRequest) -> api.SetRoiLocationReply:
        """Points the camera at a location, through MAVSDK's Gimbal plugin:
        MAV_CMD_DO_SET_ROI_LOCATION (a COMMAND_INT) to every gimbal manager.

        MAVSDK sends it in MAV_FRAME_GLOBAL_RELATIVE_ALT (its CommandInt's default
        frame, which set_roi_location leaves), so the altitude given is above home."""
        for name in ("latitude_deg", "longitude_deg"):
            if not request.HasField(name):
                raise StatusError(
                    grpc.StatusCode.INVALID_ARGUMENT,
                    f"SetRoiLocation: {name} is missing; a region of interest needs both "
                    "latitude_deg and longitude_deg",
                )
        _require_range("latitude_deg", request.latitude_deg, -90.0, 90.0)
        _require_range("longitude_deg", request.longitude_deg, -180.0, 180.0)
        _require_finite("relative_altitude_m", request.relative_altitude_m)
        home = self._cached("home")
        absolute = home.absolute_altitude_m + request.relative_altitude_m
        await self._command(
            "set region of interest",
            lambda: self._gimbal.set_roi_location(
                0, request.latitude_deg, request.longitude_deg, request.relative_altitude_m
            ),
        )
        self._roi = api.Position(
            latitude_deg=request.latitude_deg,
            longitude_deg=request.longitude_deg,
            absolute_altitude_m=absolute,
            relative_altitude_m=request.relative_altitude_m,
        )
        return api.SetRoiLocationReply()

    async def ClearRoi(self, request: api.ClearRoiRequest) -> api.ClearRoiReply:
        """Clears the region of interest (MAV_CMD_DO_SET_ROI_NONE, all gimbals)."""
        self._require_connected()
        await self._raw_command("clear region of interest", mavlink.MAV_CMD_DO_SET_ROI_NONE, 0)
        self._roi = None
        return api.ClearRoiReply()
