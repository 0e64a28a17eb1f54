"""The sim vehicle's physics: a point that climbs, flies straight and lands.

Pure and deterministic: no sockets, no clocks. The MAVLink server feeds it
commands and calls ``step(dt)`` with simulated seconds (wall seconds times the
speed-up), so every manoeuvre can be tested by stepping it by hand.

It also keeps the autopilot's estimator warm-up: a real ArduCopter has no home
for about 20 s after boot and refuses to arm for about 40 s, until its EKF
uses GPS (docs/design.md, "The real autopilot"). Code that waits for "ready" only works
against a real autopilot if the sim makes it wait too.

Positions are kept in metres north / east / up of a fixed local origin (the
initial home on the ground) and converted to WGS84 with an equirectangular
approximation, which is exact enough for missions a few kilometres wide.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, replace

EARTH_RADIUS_M = 6_371_000.0
# How close (metres) counts as "at the target", so float noise cannot keep the
# vehicle hovering a millimetre short forever.
ARRIVAL_TOLERANCE_M = 0.01
# ArduPilot repeats its pre-arm failure every 30 s (PREARM_DISPLAY_PERIOD)
# while the vehicle is disarmed and not armable.
PREARM_REPORT_PERIOD_S = 30.0
# ArduCopter's words while its EKF does not use GPS yet (AP_Arming_Copter).
NEED_POSITION_ESTIMATE = "Need Position Estimate"


@dataclass(frozen=True)
class GeoPoint:
    """A WGS84 position with altitude above mean sea level."""

    latitude_deg: float
    longitude_deg: float
    altitude_amsl_m: float


@dataclass(frozen=True)
class LocalPoint:
    """Metres north, east and up of the local origin."""

    north_m: float
    east_m: float
    up_m: float

    def horizontal_distance_to(self, other: LocalPoint) -> float:
        """Metres between the two points, ignoring altitude."""
        return math.hypot(other.north_m - self.north_m, other.east_m - self.east_m)


class Phase(enum.Enum):
    """What the vehicle is doing; the server maps it to a PX4 flight mode."""

    ON_GROUND = "on_ground"
    TAKEOFF = "takeoff"
    HOLD = "hold"
    GOTO = "goto"
    LAND = "land"
    RETURN = "return"  # flying home before it lands


class Refused(Exception):
    """A command the vehicle cannot follow in its current state."""


class PreArmFailed(Refused):
    """Arming refused by a pre-arm check; ArduPilot says so as "PreArm: <reason>"."""


class ArmCheckFailed(PreArmFailed):
    """Arming refused by a check that only arming runs: "Arm: <reason>", MAV_RESULT_FAILED."""


@dataclass(frozen=True)
class FlightParams:
    """Rates of the simulated airframe and its autopilot's warm-up, in simulated time."""

    climb_rate_m_s: float = 3.0
    descent_rate_m_s: float = 3.0
    cruise_speed_m_s: float = 5.0
    takeoff_altitude_m: float = 2.5  # PX4's MIS_TAKEOFF_ALT default
    # The fastest it flies horizontally whatever it is asked (PX4's MPC_XY_VEL_MAX and
    # its default: PX4 truncates a faster setpoint to it).
    max_speed_m_s: float = 12.0
    # The battery: its energy, and the power drawn while armed: hover power
    # plus a term growing with the square of the ground speed (drag), in
    # watts. 100 Wh at 200 W hover and 2 W/(m/s)^2 last 24 min at 5 m/s,
    # 30 min hovering: a small survey multicopter.
    battery_capacity_wh: float = 100.0
    hover_power_w: float = 200.0
    drag_power_w_per_m2s2: float = 2.0
    # Seconds from start until the estimator is ready: GPS healthy, home set,
    # armable. ArduCopter SITL takes ~40 s; 10 s costs tests 1 s at speed-up 10.
    warmup_s: float = 10.0
    # Arms refused once warmed up, as ArduPilot refuses when an arming check
    # fails between its 1 Hz pre-arm reports (the pre-arm bit still set).
    arm_refusals: int = 0


class LocalFrame:
    """Converts between WGS84 and metres around a fixed origin."""

    def __init__(self, origin: GeoPoint) -> None:
        self.origin = origin
        self._m_per_deg_lat = math.radians(1.0) * EARTH_RADIUS_M
        self._m_per_deg_lon = self._m_per_deg_lat * math.cos(math.radians(origin.latitude_deg))

    def to_local(self, point: GeoPoint) -> LocalPoint:
        """The point in metres of this frame."""
        return LocalPoint(
            north_m=(point.latitude_deg - self.origin.latitude_deg) * self._m_per_deg_lat,
            east_m=(point.longitude_deg - self.origin.longitude_deg) * self._m_per_deg_lon,
            up_m=point.altitude_amsl_m - self.origin.altitude_amsl_m,
        )

    def to_geo(self, point: LocalPoint) -> GeoPoint:
        """The point in WGS84."""
        return GeoPoint(
            latitude_deg=self.origin.latitude_deg + point.north_m / self._m_per_deg_lat,
            longitude_deg=self.origin.longitude_deg + point.east_m / self._m_per_deg_lon,
            altitude_amsl_m=self.origin.altitude_amsl_m + point.up_m,
        )


def _approach(current: float, target: float, max_step: float) -> float:
    """``current`` moved towards ``target`` by at most ``max_step``."""
    if abs(target - current) <= max_step:
        return target
    return current + math.copysign(max_step, target - current)


class Kinematics:
    """The vehicle's state machine and motion; one instance per vehicle.

    Commands raise ``Refused`` with a reason when the state does not allow
    them (arm in the air, goto on the ground, ...); ``step`` advances time.
    """

    def __init__(self, home: GeoPoint, params: FlightParams | None = None) -> None:
        self.frame = LocalFrame(home)
        self.params = params or FlightParams()
        self._arm_refusals_left = self.params.arm_refusals
        self.speed_m_s = self.params.cruise_speed_m_s
        self.takeoff_altitude_m = self.params.takeoff_altitude_m
        self.max_speed_m_s = self.params.max_speed_m_s
        self.position = LocalPoint(0.0, 0.0, 0.0)
        self.home = self.position
        self.velocity = LocalPoint(0.0, 0.0, 0.0)  # m/s, per axis
        self.heading_deg = 0.0
        self.armed = False
        self.phase = Phase.ON_GROUND
        self.target: LocalPoint | None = None
        self.battery_pct = 100.0
        self.time_s = 0.0
        self._next_prearm_report_s = 0.0

    # --- what the server reports -------------------------------------------------

    def power_w(self) -> float:
        """The power drawn now, watts: hover plus drag by the ground speed (armed on the
        ground: a tenth of hover, the motors idling)."""
        p = self.params
        if not self.in_air:
            return p.hover_power_w / 10
        speed_sq = self.velocity.north_m**2 + self.velocity.east_m**2
        return p.hover_power_w + p.drag_power_w_per_m2s2 * speed_sq

    def battery_draw_pct_s(self) -> float:
        """Percent of the battery used per simulated second now."""
        return 100.0 * self.power_w() / (self.params.battery_capacity_wh * 3600.0)

    @property
    def in_air(self) -> bool:
        """Off the ground (including while taking off and landing)."""
        return self.phase is not Phase.ON_GROUND

    @property
    def relative_altitude_m(self) -> float:
        """Height above home."""
        return self.position.up_m - self.home.up_m

    def geo_position(self) -> GeoPoint:
        """Where the vehicle is, in WGS84."""
        return self.frame.to_geo(self.position)

    def geo_home(self) -> GeoPoint:
        """Where home is, in WGS84."""
        return self.frame.to_geo(self.home)

    @property
    def estimator_ready(self) -> bool:
        """Warmed up: the GPS is healthy, home is set and the pre-arm checks pass."""
        return self.time_s >= self.params.warmup_s

    def prearm_failure(self) -> str | None:
        """Why arming would be refused now, in ArduCopter's words; None once armable."""
        return None if self.estimator_ready else NEED_POSITION_ESTIMATE

    def prearm_report_due(self) -> str | None:
        """The pre-arm failure to announce now, if one is due; it then waits a period.

        Due at the first call and every ``PREARM_REPORT_PERIOD_S`` of simulated
        time after, while disarmed and not armable, as ArduPilot repeats it:
        ground stations learn why the vehicle is not ready without trying.
        """
        failure = self.prearm_failure()
        if failure is None or self.armed or self.time_s < self._next_prearm_report_s:
            return None
        self._next_prearm_report_s = self.time_s + PREARM_REPORT_PERIOD_S
        return failure

    # --- commands ----------------------------------------------------------------

    def arm(self) -> None:
        """Arms on the ground once warmed up; home becomes the current position, as on PX4."""
        if self.armed:
            return
        if self.phase is not Phase.ON_GROUND:
            raise Refused("cannot arm in the air")
        failure = self.prearm_failure()
        if failure is not None:
            raise PreArmFailed(failure)
        if self._arm_refusals_left > 0:
            self._arm_refusals_left -= 1
            raise ArmCheckFailed("Arm: Gyros still settling")
        self.armed = True
        self.home = self.position

    def disarm(self, force: bool = False) -> None:
        """Disarms on the ground (anywhere if forced: the vehicle then drops)."""
        if not self.armed:
            return
        if self.phase is not Phase.ON_GROUND and not force:
            raise Refused("cannot disarm in the air")
        self.armed = False
        self._touch_down()

    def takeoff(self, altitude_m: float | None = None) -> None:
        """Climbs straight up to ``altitude_m`` above home (default: the takeoff altitude)."""
        if not self.armed:
            raise Refused("not armed")
        altitude = self.takeoff_altitude_m if altitude_m is None else altitude_m
        if not math.isfinite(altitude) or altitude <= 0:
            raise Refused(f"bad takeoff altitude {altitude}")
        self.target = replace(self.position, up_m=self.home.up_m + altitude)
        self.phase = Phase.TAKEOFF

    def goto(self, target: LocalPoint, speed_m_s: float | None = None) -> None:
        """Flies straight to ``target`` (horizontally at the cruise speed) and holds."""
        if self.phase is Phase.ON_GROUND:
            raise Refused("on the ground: take off first")
        if speed_m_s is not None and speed_m_s > 0:
            self.set_speed(speed_m_s)
        self.target = replace(target, up_m=max(target.up_m, self.home.up_m))
        self.phase = Phase.GOTO

    def goto_geo(self, target: GeoPoint, speed_m_s: float | None = None) -> None:
        """``goto`` with a WGS84 target (altitude AMSL)."""
        self.goto(self.frame.to_local(target), speed_m_s)

    def hold(self) -> None:
        """Stops where it is (in the air); nothing changes on the ground."""
        if self.phase is not Phase.ON_GROUND:
            self.phase = Phase.HOLD
            self.target = None

    def land(self) -> None:
        """Descends where it is and disarms on the ground."""
        if self.phase is Phase.ON_GROUND:
            return
        self.phase = Phase.LAND
        self.target = None

    def return_to_launch(self) -> None:
        """Flies home at the current altitude, then lands."""
        if self.phase is Phase.ON_GROUND:
            raise Refused("on the ground")
        self.target = replace(self.home, up_m=self.position.up_m)
        self.phase = Phase.RETURN

    def reset_battery(self, percent: float) -> None:
        """The battery reads ``percent`` from now on and drains on from there as before: a
        battery monitor's charge count set anew, as ArduPilot's MAV_CMD_BATTERY_RESET sets
        it (a pack swapped, or a fault tried on purpose). Refused unless 0-100 %."""
        if not (math.isfinite(percent) and 0.0 <= percent <= 100.0):
            raise Refused(f"battery percentage {percent} is not from 0 to 100 %")
        self.battery_pct = percent

    def set_speed(self, speed_m_s: float) -> None:
        """Sets the horizontal cruise speed of this and later gotos."""
        if not math.isfinite(speed_m_s) or speed_m_s <= 0:
            raise Refused(f"bad speed {speed_m_s}")
        self.speed_m_s = speed_m_s

    # --- time --------------------------------------------------------------------

    def step(self, dt: float) -> None:
        """Advances the simulation by ``dt`` simulated seconds."""
        if dt <= 0:
            return
        self.time_s += dt
        if self.armed:
            self.battery_pct = max(0.0, self.battery_pct - self.battery_draw_pct_s() * dt)
        before = self.position
        if self.phase is Phase.TAKEOFF:
            assert self.target is not None
            if self._move_towards(self.target, dt):
                self.hold()
        elif self.phase is Phase.GOTO:
            assert self.target is not None
            if self._move_towards(self.target, dt):
                self.hold()
        elif self.phase is Phase.RETURN:
            assert self.target is not None
            if self._move_towards(self.target, dt):
                self.land()
        elif self.phase is Phase.LAND:
            ground = 0.0
            up = max(ground, self.position.up_m - self.params.descent_rate_m_s * dt)
            self.position = replace(self.position, up_m=up)
            if up <= ground:
                self.armed = False  # PX4 disarms shortly after touching down
                self._touch_down()
        self.velocity = LocalPoint(
            (self.position.north_m - before.north_m) / dt,
            (self.position.east_m - before.east_m) / dt,
            (self.position.up_m - before.up_m) / dt,
        )

    def _move_towards(self, target: LocalPoint, dt: float) -> bool:
        """One step towards ``target``; True once there."""
        here = self.position
        distance = here.horizontal_distance_to(target)
        north, east = target.north_m, target.east_m
        reach = min(self.speed_m_s, self.max_speed_m_s) * dt
        if distance > reach:
            fraction = reach / distance
            north = here.north_m + (target.north_m - here.north_m) * fraction
            east = here.east_m + (target.east_m - here.east_m) * fraction
        if distance > ARRIVAL_TOLERANCE_M:
            self.heading_deg = (
                math.degrees(math.atan2(target.east_m - here.east_m, target.north_m - here.north_m))
                % 360.0
            )
        up = _approach(here.up_m, target.up_m, self.params.climb_rate_m_s * dt)
        self.position = LocalPoint(north, east, up)
        return (
            self.position.horizontal_distance_to(target) <= ARRIVAL_TOLERANCE_M
            and abs(self.position.up_m - target.up_m) <= ARRIVAL_TOLERANCE_M
        )

    def _touch_down(self) -> None:
        self.position = replace(self.position, up_m=0.0)
        self.phase = Phase.ON_GROUND
        self.target = None
