"""The sim vehicle's physics, stepped by hand."""

from __future__ import annotations

import math

import pytest

from baton.sim_vehicle.kinematics import (
    NEED_POSITION_ESTIMATE,
    PREARM_REPORT_PERIOD_S,
    FlightParams,
    GeoPoint,
    Kinematics,
    LocalFrame,
    LocalPoint,
    Phase,
    PreArmFailed,
    Refused,
)

HOME = GeoPoint(47.397742, 8.545594, 488.0)
# Armable at once: the flight tests below are not about the warm-up.
WARM = FlightParams(warmup_s=0.0)


def run(k: Kinematics, seconds: float, dt: float = 0.05) -> None:
    for _ in range(round(seconds / dt)):
        k.step(dt)


def airborne(altitude: float = 10.0) -> Kinematics:
    k = Kinematics(HOME, WARM)
    k.arm()
    k.takeoff(altitude)
    run(k, altitude / k.params.climb_rate_m_s + 0.5)
    assert k.phase is Phase.HOLD
    return k


def test_local_frame_round_trip_and_scale() -> None:
    frame = LocalFrame(HOME)
    point = LocalPoint(50.0, -30.0, 10.0)
    back = frame.to_local(frame.to_geo(point))
    assert back.north_m == pytest.approx(50.0)
    assert back.east_m == pytest.approx(-30.0)
    assert back.up_m == pytest.approx(10.0)
    # One degree of latitude is about 111.2 km.
    north = frame.to_geo(LocalPoint(111_195.0, 0.0, 0.0))
    assert north.latitude_deg - HOME.latitude_deg == pytest.approx(1.0, abs=1e-3)


def test_takeoff_climbs_at_the_climb_rate_then_holds() -> None:
    k = Kinematics(HOME, FlightParams(climb_rate_m_s=2.0, warmup_s=0.0))
    k.arm()
    k.takeoff(10.0)
    assert k.phase is Phase.TAKEOFF and k.in_air
    run(k, 2.5)
    assert k.relative_altitude_m == pytest.approx(5.0)
    assert k.velocity.up_m == pytest.approx(2.0)
    run(k, 3.0)
    assert k.relative_altitude_m == pytest.approx(10.0)
    assert k.phase is Phase.HOLD


def test_takeoff_defaults_to_the_takeoff_altitude_parameter() -> None:
    k = Kinematics(HOME, WARM)
    k.takeoff_altitude_m = 4.0
    k.arm()
    k.takeoff()
    run(k, 5.0)
    assert k.relative_altitude_m == pytest.approx(4.0)


def test_goto_flies_straight_at_the_cruise_speed() -> None:
    k = airborne()
    target = LocalPoint(30.0, 40.0, 10.0)  # 50 m away
    k.goto(target)
    run(k, 5.0)
    assert k.position.horizontal_distance_to(LocalPoint(0, 0, 10)) == pytest.approx(25.0)
    assert math.degrees(math.atan2(40, 30)) == pytest.approx(k.heading_deg)
    run(k, 5.5)
    assert k.position.horizontal_distance_to(target) < 0.02
    assert k.phase is Phase.HOLD


def test_set_speed_changes_the_cruise_speed() -> None:
    k = airborne()
    k.set_speed(10.0)
    k.goto(LocalPoint(100.0, 0.0, 10.0))
    run(k, 2.0)
    assert k.position.north_m == pytest.approx(20.0)
    with pytest.raises(Refused):
        k.set_speed(0.0)


def test_no_speed_asked_flies_faster_than_the_maximum() -> None:
    k = airborne()  # PX4's MPC_XY_VEL_MAX default: 12 m/s
    k.set_speed(30.0)
    k.goto(LocalPoint(100.0, 0.0, 10.0))
    run(k, 2.0)
    assert k.position.north_m == pytest.approx(24.0)


def test_goto_geo_uses_amsl_altitude() -> None:
    k = airborne()
    k.goto_geo(GeoPoint(HOME.latitude_deg, HOME.longitude_deg, HOME.altitude_amsl_m + 16.0))
    run(k, 3.0)
    assert k.relative_altitude_m == pytest.approx(16.0)
    assert k.geo_position().altitude_amsl_m == pytest.approx(504.0)


def test_land_descends_and_disarms_on_the_ground() -> None:
    k = airborne(9.0)
    k.land()
    assert k.phase is Phase.LAND
    run(k, 1.0)
    assert k.relative_altitude_m == pytest.approx(6.0)
    run(k, 2.5)
    assert k.phase is Phase.ON_GROUND and not k.armed and not k.in_air
    assert k.relative_altitude_m == 0.0


def test_return_to_launch_flies_home_then_lands() -> None:
    k = airborne()
    k.goto(LocalPoint(50.0, 0.0, 10.0))
    run(k, 11.0)
    k.return_to_launch()
    assert k.phase is Phase.RETURN
    run(k, 10.5)
    assert k.phase is Phase.LAND
    assert k.position.horizontal_distance_to(k.home) < 0.02
    run(k, 4.0)
    assert k.phase is Phase.ON_GROUND and not k.armed


def test_hold_stops_a_goto() -> None:
    k = airborne()
    k.goto(LocalPoint(100.0, 0.0, 10.0))
    run(k, 2.0)
    k.hold()
    stopped = k.position
    run(k, 2.0)
    assert k.position == stopped and k.phase is Phase.HOLD


def test_refusals() -> None:
    k = Kinematics(HOME, WARM)
    with pytest.raises(Refused, match="not armed"):
        k.takeoff(10.0)
    with pytest.raises(Refused, match="take off first"):
        k.goto(LocalPoint(1.0, 1.0, 10.0))
    with pytest.raises(Refused):
        k.return_to_launch()
    k = airborne()
    with pytest.raises(Refused, match="disarm in the air"):
        k.disarm()
    k.disarm(force=True)
    assert not k.armed and k.phase is Phase.ON_GROUND


def test_arming_sets_home_and_battery_drains_only_when_armed() -> None:
    """36 Wh: 1 % is 1296 J; armed on the ground a tenth of the 200 W hover draw."""
    k = Kinematics(HOME, FlightParams(battery_capacity_wh=36.0, warmup_s=0.0))
    run(k, 1.0)
    assert k.battery_pct == 100.0
    k.arm()
    run(k, 2.0)
    assert k.battery_pct == pytest.approx(100.0 - 2 * 20.0 / 1296.0)
    assert k.geo_home() == HOME


def test_the_battery_drains_by_hover_and_by_speed() -> None:
    """In the air: hover power plus drag by the square of the ground speed."""
    params = FlightParams(
        battery_capacity_wh=36.0, hover_power_w=200.0, drag_power_w_per_m2s2=2.0, warmup_s=0.0
    )
    k = Kinematics(HOME, params)
    k.arm()
    k.takeoff(10.0)
    run(k, 10.0)
    hovering = k.battery_draw_pct_s()
    assert k.power_w() == pytest.approx(200.0)
    assert hovering == pytest.approx(100 * 200.0 / (36.0 * 3600))
    k.goto(LocalPoint(1000.0, 0.0, 10.0))
    run(k, 10.0)
    assert k.power_w() == pytest.approx(200.0 + 2.0 * 5.0**2)  # cruising at 5 m/s


def test_a_battery_reset_reads_its_percentage_and_drains_on_from_there() -> None:
    """MAV_CMD_BATTERY_RESET's effect: the reading is set, the draw goes on as before;
    a percentage that is not one is refused and changes nothing."""
    k = Kinematics(HOME, FlightParams(battery_capacity_wh=36.0, warmup_s=0.0))
    k.arm()
    run(k, 5.0)
    k.reset_battery(15.0)
    assert k.battery_pct == 15.0
    run(k, 2.0)
    assert k.battery_pct == pytest.approx(15.0 - 2 * 20.0 / 1296.0)
    for bad in (-0.5, 100.5, math.nan, math.inf):
        with pytest.raises(Refused, match="is not from 0 to 100 %"):
            k.reset_battery(bad)
    assert k.battery_pct == pytest.approx(15.0 - 2 * 20.0 / 1296.0)


def test_not_armable_until_the_estimator_has_warmed_up() -> None:
    k = Kinematics(HOME, FlightParams(warmup_s=40.0))
    assert not k.estimator_ready
    assert k.prearm_failure() == NEED_POSITION_ESTIMATE
    with pytest.raises(PreArmFailed, match=NEED_POSITION_ESTIMATE) as refused:
        k.arm()
    assert isinstance(refused.value, Refused)  # the server DENIES it like any refusal
    assert not k.armed
    k.step(39.5)
    assert not k.estimator_ready
    with pytest.raises(PreArmFailed):
        k.arm()
    k.step(0.5)  # exactly 40 s of simulated time
    assert k.estimator_ready and k.prearm_failure() is None
    k.arm()
    assert k.armed


def test_the_default_warmup_is_ten_simulated_seconds() -> None:
    k = Kinematics(HOME)
    k.step(9.75)
    assert not k.estimator_ready
    k.step(0.25)
    assert k.estimator_ready


def test_prearm_failure_is_reported_at_once_then_every_period() -> None:
    k = Kinematics(HOME, FlightParams(warmup_s=100.0))
    assert k.prearm_report_due() == NEED_POSITION_ESTIMATE
    assert k.prearm_report_due() is None  # once per period, however often asked
    k.step(PREARM_REPORT_PERIOD_S - 0.5)
    assert k.prearm_report_due() is None
    k.step(0.5)
    assert k.prearm_report_due() == NEED_POSITION_ESTIMATE
    k.step(PREARM_REPORT_PERIOD_S)
    assert k.prearm_report_due() == NEED_POSITION_ESTIMATE
    k.step(100.0 - k.time_s)
    assert k.estimator_ready
    k.step(PREARM_REPORT_PERIOD_S)
    assert k.prearm_report_due() is None  # armable: nothing to say


def test_a_warmed_up_vehicle_reports_nothing() -> None:
    k = Kinematics(HOME, WARM)
    assert k.estimator_ready and k.prearm_report_due() is None
    k.arm()
    assert k.prearm_report_due() is None
