"""The operator's safety net, as pure decisions: the failsafe a vehicle is in, the
limits a vehicle can fly, the station to land at.

No clock, no I/O: ``DroneCore`` holds a ``Failsafe`` and asks these functions;
the drone service and the simulation's drone carry out what it decides, and
the controller asks ``sleep_refusal`` before it sleeps (docs/operating.md,
"The safety net").
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

import grpc
from google.protobuf.message import Message

from baton.drone.fence import breach
from baton.drone.policy import Fix, Station, distance_m
from baton.rpc.errors import StatusError
from baton.sdk.fence import Fence
from baton.sdk.types import Position
from baton.v1 import drone_api_pb2 as api

# What a failsafe makes the vehicle do.
ACTIONS = ("hold", "land", "rtl", "nearest_station")


@dataclass(frozen=True)
class SafetyParams:
    """The safety net's settings, in wall seconds (``config.SafetyConfig`` / speed-up)."""

    lost_link_s: float = 0.0  # 0: no lost-link failsafe
    lost_link_action: str = "rtl"
    max_speed_m_s: float = math.inf
    max_altitude_m: float = math.inf
    battery_reserve_pct: float = 0.0  # 0: no battery reserve
    battery_action: str = "rtl"
    fence: Fence | None = None  # None: no fence (drone/fence.py)


@dataclass(frozen=True)
class Failsafe:
    """The vehicle taken out of the mission's hands: why (``cause``: ``lost_link``,
    ``battery``, ``fence`` or ``autopilot``),
    what it does (``action``, and the ``station`` it flies to for nearest_station),
    since when (wall seconds) and the reason a person reads."""

    cause: str
    action: str
    since: float
    reason: str
    station: int | None = None

    @property
    def drone_acts(self) -> bool:
        """Whether the drone commands the vehicle the action: not when the autopilot took
        the vehicle over (``AUTOPILOT``), which flies it already (or a pilot does)."""
        return self.cause != AUTOPILOT

    def refusal(self, method: str) -> StatusError:
        """What a call gets while the vehicle is in this failsafe: refused before execution."""
        return StatusError(
            grpc.StatusCode.FAILED_PRECONDITION,
            f"{method}: the vehicle is in failsafe ({self.cause}: {self.reason}); nothing was "
            "executed. An operator's Resume (Drone.Resume) gives the mission the vehicle back",
        )


def lost_link_failsafe(
    now: float, last_usable: float, params: SafetyParams, station: int | None
) -> Failsafe | None:
    """The lost-link failsafe due at ``now`` when no usable controller was there since
    ``last_usable``; None while the link was lost for less than ``lost_link_s``."""
    lost_s = now - last_usable
    if params.lost_link_s <= 0 or lost_s < params.lost_link_s:
        return None
    action, where = _landing_action(params.lost_link_action, station)
    return Failsafe(
        "lost_link",
        action,
        now,
        f"no usable controller for {lost_s:.1f} s (lost_link {params.lost_link_s:g} s): "
        f"{action}{where}",
        station if action == "nearest_station" else None,
    )


def battery_failsafe(
    now: float, percent: float, params: SafetyParams, station: int | None
) -> Failsafe | None:
    """The battery failsafe due at ``now`` with ``percent`` left: below the mission's
    reserve, the mission ends with ``battery_action``; None above it, when the reserve
    is off, or when the autopilot does not say (NaN)."""
    reserve = params.battery_reserve_pct
    if reserve <= 0 or not math.isfinite(percent) or percent >= reserve:
        return None
    action, where = _landing_action(params.battery_action, station)
    return Failsafe(
        "battery",
        action,
        now,
        f"battery {percent:.1f} % below the reserve of {reserve:g} %: {action}{where}",
        station if action == "nearest_station" else None,
    )


def fence_failsafe(now: float, position: api.Position, fence: Fence | None) -> Failsafe | None:
    """The fence failsafe due at ``now`` with the vehicle at ``position`` (its telemetry):
    out of the fence (wind, a ground station's command), the fence's action; None while
    it is inside or there is no fence."""
    why = breach(fence, position)
    if fence is None or why is None:
        return None
    at = (
        f"({position.latitude_deg:.7f}, {position.longitude_deg:.7f}, "
        f"{position.relative_altitude_m:.1f} m)"
    )
    return Failsafe(
        "fence", fence.action, now, f"fence breach: the vehicle at {at} is {why}: {fence.action}"
    )


# -- the autopilot taking the vehicle over ------------------------------------------

# The cause of the failsafe the autopilot's own decision puts the vehicle in.
AUTOPILOT = "autopilot"
# What the drone last commanded the vehicle, by the flight modes it may then be in.
FLY, HOLD, LAND, RTL = "fly", "hold", "land", "rtl"
# Flight modes by name: ArduPilot's own (its heartbeat's custom mode, as pymavlink names
# it: MAVSDK names GUIDED "OFFBOARD" and both BRAKE and LOITER "HOLD"), else MAVSDK's
# (PX4 and the sim vehicle). The drone flies a mission in these: ArduPilot's GUIDED;
# PX4's Hold (it flies a reposition in it), Takeoff and Offboard.
_FLYING = frozenset({"GUIDED", "GUIDED_NOGPS", "OFFBOARD", "HOLD", "TAKEOFF"})
# MAVSDK's Hold is BRAKE on ArduCopter, LOITER on other frames; POSHOLD for safety.
_HOLDING = _FLYING | {"BRAKE", "LOITER", "POSHOLD"}
_LANDING = _FLYING | {"LAND", "QLAND"}
# A return ends in a landing, in a mode of its own on some firmware.
_RETURNING = _LANDING | {"RTL", "SMART_RTL", "AUTO_RTL", "QRTL", "RETURN_TO_LAUNCH"}
EXPECTED_MODES = {FLY: _FLYING, HOLD: _HOLDING, LAND: _LANDING, RTL: _RETURNING}
# Mode names that say nothing (not known yet, PX4's READY on the ground).
_UNKNOWN_MODES = frozenset({"", "UNKNOWN", "READY"})
# Each Mobility command the drone executes, by what it commands (reads and SetSpeed
# change no mode).
VEHICLE_ACTIONS = {
    "Arm": FLY,
    "Takeoff": FLY,
    "Goto": FLY,
    "Hold": HOLD,
    "Land": LAND,
    "Disarm": LAND,
    "ReturnToLaunch": RTL,
}
# What a failsafe's or an operator's action commands (a resume flying on is a "goto").
_ACTION_COMMANDS = {
    "hold": HOLD,
    "land": LAND,
    "rtl": RTL,
    "nearest_station": FLY,
    "goto": FLY,
}
# After a command, the vehicle's reported mode is not read for this long (wall seconds):
# ArduPilot says its mode in its heartbeat, once a second, and MAVSDK passes it on.
MODE_SETTLE_S = 3.0


def commanded_action(action: str) -> str | None:
    """What a failsafe's or an operator's ``action`` commands the vehicle (``FLY``,
    ``HOLD``, ``LAND``, ``RTL``); None when it commands nothing."""
    return _ACTION_COMMANDS.get(action)


@dataclass(frozen=True)
class ModeSeen:
    """The vehicle as the autopilot reports it: its flight mode, armed, in the air."""

    mode: str
    armed: bool
    in_air: bool


def mode_seen(state: api.GetFlightStateReply) -> ModeSeen:
    """The vehicle's flight ``state`` as the takeover rule reads it: ArduPilot's own mode
    name, else MAVSDK's."""
    mode = state.autopilot_mode if state.autopilot == "ArduPilot" else state.flight_mode
    return ModeSeen(mode, state.armed, state.in_air)


@dataclass(frozen=True)
class VehicleCommand:
    """What the drone last commanded the vehicle: the ``actions`` whose modes it may be in
    (two while a command executes, and after one that failed: the vehicle may have taken
    it or not), since when (wall seconds), the ``before`` ones it may still be in for
    ``MODE_SETTLE_S`` after (its mode is reported late), whether the vehicle was seen in
    the air since, and a mode an operator's resume took as it was (``accepted``: a
    ground station's or the autopilot's, until the next command)."""

    actions: tuple[str, ...]
    at: float
    before: tuple[str, ...] = ()
    airborne: bool = False
    accepted: str = ""

    def commanding(self, action: str, now: float) -> VehicleCommand:
        """A command for ``action`` is being sent: either mode may follow."""
        actions = tuple(dict.fromkeys((*self.actions, action)))
        return VehicleCommand(actions, now, self.allowed(now), self.airborne)

    def commanded(self, action: str, now: float) -> VehicleCommand:
        """The vehicle accepted the command for ``action``: its modes are expected from
        now, the earlier ones for ``MODE_SETTLE_S`` more. A vehicle seen in the air stays
        so through a command that keeps it flying or holding (a kill of the drone right
        after it must still know it flew: ``landed_while_down``); after a landing or a
        return in the air or not is looked at afresh (a new flight starts on the ground)."""
        earlier = tuple(dict.fromkeys((*self.before, *self.actions)))
        flies_on = self.airborne and action in (FLY, HOLD) and not {LAND, RTL} & set(earlier)
        return VehicleCommand((action,), now, earlier, flies_on)

    def unseen(self) -> VehicleCommand:
        """The vehicle's state is not known now (its link is out, or it rebooted): it
        counts as seen in the air again only once it reports it; a vehicle that comes
        back on the ground is the link's outage (GetStatus.vehicle), not a takeover."""
        return replace(self, airborne=False)

    def allowed(self, now: float) -> tuple[str, ...]:
        """The actions whose modes the vehicle may be in at ``now``."""
        settling = now - self.at < MODE_SETTLE_S
        return tuple(dict.fromkeys((*self.actions, *self.before))) if settling else self.actions

    def expects(self, mode: str, now: float) -> bool:
        """Whether the vehicle may be in ``mode`` at ``now`` for what the drone commanded."""
        if mode in _UNKNOWN_MODES or mode == self.accepted:
            return True
        return any(mode in EXPECTED_MODES[a] for a in self.allowed(now))


def autopilot_takeover(
    now: float, command: VehicleCommand, seen: ModeSeen
) -> tuple[VehicleCommand, Failsafe | None]:
    """The autopilot taking the vehicle over, decided from what the drone ``command``ed
    and what it reports (``seen``): in the air, a flight mode no command of the drone
    explains, or a vehicle seen in the air since the command that lands or disarms
    while the drone flies it, is the autopilot's own decision (its fence, battery or
    GCS failsafe, a pilot's mode switch). Returns the command with what was seen (in
    the air) and the failsafe due; None while none is."""
    if seen.in_air and seen.armed and not command.airborne:
        command = replace(command, airborne=True)
    allowed = command.allowed(now)
    said = "/".join(allowed)
    # Landing is the vehicle's own once it was commanded to land or return, and after a
    # resume took its mode as it was (that mode may land it).
    flying = not set(allowed) & {LAND, RTL} and not command.accepted
    if command.airborne and flying and not (seen.armed and seen.in_air):
        what = "landed" if not seen.in_air else "disarmed"
        return command, Failsafe(
            AUTOPILOT,
            what,
            now,
            f"autopilot took over: the vehicle {what} while the drone flew it ({said}); "
            "the drone commands nothing",
        )
    if not seen.in_air or command.expects(seen.mode, now):
        return command, None
    return command, Failsafe(
        AUTOPILOT,
        seen.mode,
        now,
        f"autopilot took over: {seen.mode} (the drone commanded {said}); the drone "
        "commands nothing",
    )


def landed_while_down(now: float, command: VehicleCommand, seen: ModeSeen) -> Failsafe | None:
    """The first sight of the vehicle after a restart of the drone service, which had seen
    it in the air flying the mission (``command``): on the ground or disarmed, the
    autopilot took it over meanwhile (its own GCS failsafe, with no drone speaking to it),
    and the mission must not poll a vehicle that will never arrive; None otherwise, or
    if the drone had commanded it to land or return."""
    if set(command.actions) & {LAND, RTL} or (seen.armed and seen.in_air):
        return None
    what = "landed" if not seen.in_air else "disarmed"
    return Failsafe(
        AUTOPILOT,
        what,
        now,
        f"autopilot took over: the vehicle {what} while the drone service was down (it "
        f"flew {'/'.join(command.actions)}); the drone commands nothing",
    )


def _landing_action(action: str, station: int | None) -> tuple[str, str]:
    """The action and its words: nearest_station needs a station, else home (rtl)."""
    if action != "nearest_station":
        return action, ""
    if station is None:
        return "rtl", " (no station known: rtl)"
    return action, f" (station {station})"


def nearest_station(position: api.Position, stations: Mapping[int, Station]) -> int | None:
    """The id of the station nearest ``position`` (its landing point is its location);
    None without a station or a known position."""
    if not stations or not (position.latitude_deg or position.longitude_deg):
        return None
    fix = Fix(Position.from_proto(position))
    return min(stations, key=lambda sid: (distance_m(stations[sid], fix), sid))


# Over a station's landing point within this many metres: land (nearest_station).
LANDING_RADIUS_M = 3.0


def landing_due(position: api.Position, station: Station) -> bool:
    """Whether a vehicle flying to ``station`` (nearest_station) is over it: time to land."""
    if not (position.latitude_deg or position.longitude_deg):
        return False
    return distance_m(station, Fix(Position.from_proto(position))) <= LANDING_RADIUS_M


@dataclass(frozen=True)
class AutopilotParam:
    """One parameter the drone sets on the autopilot (``gcs_failsafe_params``,
    ``fence_params``) or reads (``limit_params``). ``bits``: an integer bitmask whose
    bits of ``value`` are set over what the autopilot holds, its other bits kept."""

    name: str
    value: float
    integer: bool = True
    bits: bool = False


def gcs_failsafe_params(ardupilot: bool, timeout_s: float, gcs_sysid: int) -> list[AutopilotParam]:
    """The autopilot's own GCS failsafe, so that it returns home if the drone service
    (its only ground station) stops sending heartbeats for ``timeout_s``; [] when 0.

    ArduPilot: FS_GCS_ENABLE 1 (RTL), FS_GCS_TIMEOUT, and SYSID_MYGCS set to the drone
    service's MAVLink system id (ArduPilot counts only that id's heartbeats as its
    GCS's). PX4: NAV_DLL_ACT 2 (Return), COM_DL_LOSS_T (whole seconds, at least 5)."""
    if timeout_s <= 0:
        return []
    if ardupilot:
        return [
            AutopilotParam("SYSID_MYGCS", gcs_sysid),
            AutopilotParam("FS_GCS_TIMEOUT", max(2.0, timeout_s), integer=False),
            AutopilotParam("FS_GCS_ENABLE", 1),
        ]
    return [
        AutopilotParam("COM_DL_LOSS_T", max(5, math.ceil(timeout_s))),
        AutopilotParam("NAV_DLL_ACT", 2),
    ]


# FENCE_TYPE's bit of the maximum-altitude fence (ArduPilot's AC_FENCE_TYPE_ALT_MAX).
_ALT_MAX = 1


def fence_params(ardupilot: bool, fence: Fence) -> list[AutopilotParam]:
    """The autopilot's own fence, beside the polygons and circles uploaded to it: its
    ceiling and the action of a breach it finds itself (rtl: return, land: land), so a
    vehicle out of its fence comes back even with the drone service gone.

    ArduPilot: FENCE_TYPE's polygon bit (4) and, with a ceiling, its maximum-altitude
    bit (1) set over the bits it has, FENCE_ALT_MAX, FENCE_ACTION (1: RTL or land,
    2: land), then FENCE_ENABLE 1. PX4: GF_MAX_VER_DIST, GF_ACTION (3: Return, 5: Land).
    A fence without a ceiling leaves the autopilot's own ceiling as it is (the drone
    then reads it as the vehicle's bound: ``limit_params``)."""
    ceiling = fence.ceiling_m if math.isfinite(fence.ceiling_m) else 0.0
    if ardupilot:
        params = [AutopilotParam("FENCE_TYPE", 4 | (_ALT_MAX if ceiling else 0), bits=True)]
        if ceiling:
            params.append(AutopilotParam("FENCE_ALT_MAX", ceiling, integer=False))
        return [
            *params,
            AutopilotParam("FENCE_ACTION", 2 if fence.action == "land" else 1),
            AutopilotParam("FENCE_ENABLE", 1),
        ]
    params = [AutopilotParam("GF_MAX_VER_DIST", ceiling, integer=False)] if ceiling else []
    return [*params, AutopilotParam("GF_ACTION", 5 if fence.action == "land" else 3)]


# Where a bound in force comes from (``Bound.source``).
CONFIGURED, FROM_AUTOPILOT = "configured", "read from the autopilot"


@dataclass(frozen=True)
class VehicleLimits:
    """The bounds the autopilot says it flies within, each with the parameter that says
    it (inf, "": it says none): its horizontal speed, its ceiling above home."""

    speed_m_s: float = math.inf
    speed_param: str = ""
    altitude_m: float = math.inf
    altitude_param: str = ""


@dataclass(frozen=True)
class Bound:
    """One bound in force: its value (inf: none), what names it (``safety.max_speed``,
    an autopilot parameter) and where it came from (``CONFIGURED``, ``FROM_AUTOPILOT``)."""

    value: float
    name: str
    source: str

    def words(self) -> str:
        """The bound as a refusal names it."""
        if self.source == CONFIGURED:
            return f"the bound {self.name} = {self.value:g}"
        return f"the vehicle's bound {self.name} = {self.value:g} ({self.source})"


def _smaller(configured: Bound, vehicle_value: float, param: str) -> Bound:
    """The configured bound, or the vehicle's where it is smaller (a tie: the
    configuration's, which the operator wrote)."""
    if param and vehicle_value < configured.value:
        return Bound(vehicle_value, param, FROM_AUTOPILOT)
    return configured


def speed_bound(params: SafetyParams, vehicle: VehicleLimits) -> Bound:
    """The fastest a SetSpeed may ask: ``safety.max_speed`` or the autopilot's, the smaller."""
    configured = Bound(params.max_speed_m_s, "safety.max_speed", CONFIGURED)
    return _smaller(configured, vehicle.speed_m_s, vehicle.speed_param)


def altitude_bound(params: SafetyParams, vehicle: VehicleLimits) -> Bound:
    """The highest a Takeoff or Goto may ask (metres above home): ``safety.max_altitude``
    or the autopilot's ceiling, the smaller."""
    configured = Bound(params.max_altitude_m, "safety.max_altitude", CONFIGURED)
    return _smaller(configured, vehicle.altitude_m, vehicle.altitude_param)


def limit_params(ardupilot: bool, own_ceiling: bool) -> list[AutopilotParam]:
    """The parameters that say the autopilot's bounds (``vehicle_limits`` reads them).

    PX4: MPC_XY_VEL_MAX (m/s, the absolute maximum of every velocity-controlled mode),
    GF_MAX_VER_DIST (m above home, 0: none). ArduPilot: FENCE_ALT_MAX where FENCE_ENABLE
    is 1 and FENCE_TYPE has its maximum-altitude bit (1); ArduPilot has no hard maximum
    of horizontal speed (WPNAV_SPEED is the default a reposition flies at). With
    ``own_ceiling`` the drone sets the ceiling parameters itself (``fence_params``) from
    the mission's fence, which refuses above it already: they are not read again."""
    if ardupilot:
        if own_ceiling:
            return []
        return [
            AutopilotParam("FENCE_ENABLE", 0),
            AutopilotParam("FENCE_TYPE", 0),
            AutopilotParam("FENCE_ALT_MAX", 0, integer=False),
        ]
    speed = [AutopilotParam("MPC_XY_VEL_MAX", 0, integer=False)]
    return speed if own_ceiling else [*speed, AutopilotParam("GF_MAX_VER_DIST", 0, integer=False)]


def vehicle_limits(ardupilot: bool, values: Mapping[str, float]) -> VehicleLimits:
    """The autopilot's bounds from the ``values`` of ``limit_params`` it answered (a
    parameter it lacks is absent: it says no bound there); a value of 0 or less, or not
    finite, is no bound."""

    def positive(name: str) -> float | None:
        value = values.get(name)
        return value if value is not None and math.isfinite(value) and value > 0 else None

    speed = None if ardupilot else positive("MPC_XY_VEL_MAX")
    if ardupilot:
        fenced = values.get("FENCE_ENABLE") == 1 and int(values.get("FENCE_TYPE", 0)) & _ALT_MAX
        ceiling_param = "FENCE_ALT_MAX"
        ceiling = positive(ceiling_param) if fenced else None
    else:
        ceiling_param = "GF_MAX_VER_DIST"
        ceiling = positive(ceiling_param)
    return VehicleLimits(
        speed if speed is not None else math.inf,
        "MPC_XY_VEL_MAX" if speed is not None else "",
        ceiling if ceiling is not None else math.inf,
        ceiling_param if ceiling is not None else "",
    )


def limit_refusal(
    method: str, request: Message, params: SafetyParams, vehicle: VehicleLimits | None = None
) -> StatusError | None:
    """INVALID_ARGUMENT naming the bound a call asks beyond and where it came from (a
    SetSpeed faster than ``speed_bound``, a Takeoff or Goto higher than
    ``altitude_bound``); None if none."""
    vehicle = vehicle or VehicleLimits()
    if isinstance(request, api.SetSpeedRequest):
        return _beyond(method, "speed_m_s", request.speed_m_s, speed_bound(params, vehicle))
    if isinstance(request, api.TakeoffRequest):
        return _beyond(method, "altitude_m", request.altitude_m, altitude_bound(params, vehicle))
    if isinstance(request, api.GotoRequest):
        return _beyond(
            method,
            "relative_altitude_m",
            request.relative_altitude_m,
            altitude_bound(params, vehicle),
        )
    return None


def sleep_refusal(seconds: float, max_sleep_s: float) -> StatusError | None:
    """INVALID_ARGUMENT for a Clock.Sleep longer than the mission's ``max_sleep``; None
    if the controller may sleep it (a sleep not finite or negative is refused before it
    takes a request number: ``controller.service``)."""
    return _beyond(
        "Clock.Sleep", "seconds", seconds, Bound(max_sleep_s, "safety.max_sleep", CONFIGURED)
    )


def _beyond(method: str, field: str, value: float, bound: Bound) -> StatusError | None:
    """INVALID_ARGUMENT naming ``bound`` when ``value`` is beyond it; None otherwise."""
    if not value > bound.value:  # NaN is the execution's to refuse (not finite)
        return None
    return StatusError(
        grpc.StatusCode.INVALID_ARGUMENT,
        f"{method}: {field} {value:g} is beyond {bound.words()}; nothing was executed",
    )
