"""The drone's view of its autopilot (``vehicle_state``): link health, readiness, mode names."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import common as mavlink

from baton.drone.vehicle_state import Health as VehicleHealth
from baton.drone.vehicle_state import (
    Heartbeat,
    LinkMonitor,
    flight_state_missing,
    is_prearm_text,
    readiness,
)


def Health(
    is_global_position_ok: bool = True, is_home_position_ok: bool = True, is_armable: bool = True
) -> VehicleHealth:
    return VehicleHealth(is_global_position_ok, is_home_position_ok, is_armable)


def sys_status(present: int, enabled: int, health: int) -> dict[str, int]:
    return {
        "onboard_control_sensors_present": present,
        "onboard_control_sensors_enabled": enabled,
        "onboard_control_sensors_health": health,
    }


def test_health_from_sys_status_by_mavsdks_rules() -> None:
    gps, prearm = mavlink.MAV_SYS_STATUS_SENSOR_GPS, mavlink.MAV_SYS_STATUS_PREARM_CHECK
    everything = gps | prearm
    ok = VehicleHealth.from_messages(sys_status(everything, everything, everything), True)
    assert ok == Health()
    # GPS present and enabled but unhealthy (an estimator not using it yet), no pre-arm bit.
    warming = VehicleHealth.from_messages(sys_status(everything, everything, 0), False)
    assert warming == Health(False, False, False)
    # Healthy but not enabled is not a global position; the pre-arm bit alone is armable.
    disabled = VehicleHealth.from_messages(sys_status(everything, prearm, everything), True)
    assert not disabled.is_global_position_ok and disabled.is_armable


def test_ardupilot_has_a_global_position_once_its_ekf_uses_gps() -> None:
    everything = mavlink.MAV_SYS_STATUS_SENSOR_GPS | mavlink.MAV_SYS_STATUS_PREARM_CHECK
    status = sys_status(everything, everything, everything)
    # Flags measured on ArduCopter SITL: 0xa7 with a GPS fix, 0x33f once the EKF uses it.
    aligning = VehicleHealth.from_messages(status, True, ekf_flags=0xA7)
    assert not aligning.is_global_position_ok and aligning.is_armable
    assert VehicleHealth.from_messages(status, True, ekf_flags=0x33F) == Health()
    assert not VehicleHealth.from_messages(
        status, True, ekf_flags=0x33F | 128
    ).is_global_position_ok


def copter(custom_mode: int, autopilot: int = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA) -> Heartbeat:
    return Heartbeat(
        autopilot=autopilot,
        vehicle_type=mavlink.MAV_TYPE_QUADROTOR,
        base_mode=mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
        custom_mode=custom_mode,
    )


def test_ardupilot_modes_by_their_own_names() -> None:
    assert copter(4).mode_name() == "GUIDED"  # MAVSDK calls it OFFBOARD
    assert copter(17).mode_name() == "BRAKE"  # MAVSDK's "Hold" on a copter
    assert copter(9).mode_name() == "LAND"
    assert copter(0).autopilot_name() == "ArduPilot" and copter(0).is_ardupilot
    assert copter(0).custom_mode_number("GUIDED") == 4
    assert copter(0).custom_mode_number("NO_SUCH_MODE") is None


def test_px4_modes_and_other_autopilots() -> None:
    loiter = (4 << 16) | (3 << 24)  # AUTO main mode, LOITER sub mode
    px4 = copter(loiter, autopilot=mavlink.MAV_AUTOPILOT_PX4)
    assert px4.mode_name() == "LOITER" and px4.autopilot_name() == "PX4"
    assert not px4.is_ardupilot and px4.custom_mode_number("GUIDED") is None
    assert copter(0, autopilot=mavlink.MAV_AUTOPILOT_GENERIC).autopilot_name() == "GENERIC"


def test_ready_needs_position_home_and_prearm() -> None:
    assert readiness(Health(), armed=False, prearm_text=None).ready
    # ArduCopter ~20 s after boot: a fix and a home, EKF not using GPS yet.
    early = readiness(
        Health(is_global_position_ok=False, is_armable=False),
        False,
        "PreArm: Need Position Estimate",
    )
    assert not early.ready and not early.armable
    assert early.reason.startswith("PreArm: Need Position Estimate (")
    assert "no global position yet" in early.reason and "pre-arm checks failing" in early.reason
    # Pre-arm bit set in STABILIZE (no GPS needed there) is not armable for a mission.
    stabilize = readiness(Health(is_global_position_ok=False), False, None)
    assert not stabilize.armable and not stabilize.ready
    no_home = readiness(Health(is_home_position_ok=False), False, None)
    assert no_home.armable and not no_home.ready and no_home.reason == "no home position yet"
    assert readiness(None, False, None).reason.startswith("no health report")


def test_armed_vehicle_stays_ready_whatever_its_prearm_bit() -> None:
    flying = readiness(Health(is_armable=False), armed=True, prearm_text="PreArm: stale")
    assert flying.ready and flying.reason == ""


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("PreArm: Need Position Estimate", True),
        ("Arm: Mode not armable", True),
        ("Preflight Fail: ekf2 missing data", True),
        ("EKF3 IMU0 is using GPS", False),
    ],
)
def test_prearm_texts(text: str, expected: bool) -> None:
    assert is_prearm_text(text) is expected


def test_link_outage_and_recovery() -> None:
    link = LinkMonitor(heartbeat_timeout_s=3.0, position_max_age_s=1.0)
    assert link.problem(0.0) == "no heartbeat from the autopilot yet"
    link.heard(0.0)
    assert "no position telemetry yet" in link.problem(0.1)
    assert link.update(0.1) is None  # never healthy yet: not an outage
    link.position(0.2)
    assert link.healthy(0.5) and link.update(0.5) is None
    # The autopilot dies: MAVSDK still says connected, the position ages.
    assert link.healthy(1.2)
    assert "position telemetry 1.1 s old" in link.problem(1.3)
    assert link.update(1.3) == "outage" and link.outages == 1
    assert link.update(2.0) is None
    assert link.problem(3.5) == "no heartbeat for 3.5 s"
    snapshot = link.snapshot(3.5)
    # The outage began when the position passed its bound (0.2 + 1.0), not when noticed.
    assert not snapshot.healthy and snapshot.outage_s == pytest.approx(2.3)
    assert snapshot.heartbeat_age_s == pytest.approx(3.5)
    link.heard(10.0)
    link.position(10.0)
    assert link.update(10.1) == "recovered"
    assert link.snapshot(10.1).outage_s == 0 and link.snapshot(10.1).healthy


def test_streams_are_requested_on_contact_and_again_when_they_stop() -> None:
    link = LinkMonitor(heartbeat_timeout_s=3.0, position_max_age_s=1.0, stream_retry_s=2.0)
    assert not link.wants_streams(0.0)  # nobody to ask
    link.heard(0.0)
    assert link.wants_streams(0.0)
    link.streams_requested(0.0)
    link.heard(1.0)
    assert not link.wants_streams(1.0)  # asked just now: give it time
    assert link.wants_streams(2.0)  # still nothing: ask again
    link.streams_requested(2.0)
    link.position(2.1)
    link.status(2.1)
    link.heard(2.1)
    assert not link.wants_streams(2.5)
    # A reboot: heartbeats come back within the timeout, the streams do not.
    link.heard(6.0)
    assert link.wants_streams(6.0) and link.stream_requests == 2
    # A dead autopilot is not asked.
    assert not link.wants_streams(20.0)


def test_streams_are_requested_when_another_station_asked_for_the_position_only() -> None:
    # A second ground station asked for GLOBAL_POSITION_INT; the autopilot sends it
    # to every station, but nobody asked for SYS_STATUS, which readiness needs.
    link = LinkMonitor(heartbeat_timeout_s=3.0, position_max_age_s=1.0, stream_retry_s=2.0)
    link.heard(0.0)
    link.position(0.0)
    assert link.wants_streams(0.0)
    link.streams_requested(0.0)
    link.status(2.0)
    link.position(2.0)
    link.heard(2.0)
    assert not link.wants_streams(2.5)
    link.heard(5.5)
    link.position(5.5)  # SYS_STATUS stopped (a reboot that kept someone's position stream)
    assert not link.wants_streams(4.9)  # 2.9 s old: within its bound
    assert link.wants_streams(5.5)


def test_a_flight_state_is_known_only_once_armed_and_in_air_both_arrived() -> None:
    """Position telemetry (the link counts as up) may come before the landed state: a flight
    state then would say "on the ground" for a vehicle that hovers (a restarted drone's
    first look took it for one its autopilot landed). It is not known until both came."""
    assert flight_state_missing({"position"}) == (
        "armed state (HEARTBEAT) and landed state (EXTENDED_SYS_STATE)"
    )
    assert flight_state_missing({"position", "armed"}) == "landed state (EXTENDED_SYS_STATE)"
    assert flight_state_missing({"armed", "in_air"}) is None


def test_the_set_up_is_due_at_each_contact_whether_or_not_the_streams_flow() -> None:
    # A restarted drone service: the autopilot streams at the rates the one before asked
    # for, so the streams are not asked for; fence, failsafe and bounds are due all the same.
    link = LinkMonitor(heartbeat_timeout_s=3.0, position_max_age_s=1.0, stream_retry_s=2.0)
    assert not link.wants_set_up(0.0)  # nobody to set up
    link.heard(0.0)
    link.position(0.0)
    link.status(0.0)
    assert not link.wants_streams(0.0)
    assert link.wants_set_up(0.0)
    link.setting_up()
    assert link.update(0.5) is None and not link.wants_set_up(0.5)  # once per contact
    # Streams asked for again (a reboot, a station asking for the position alone): the
    # set-up is due again, for an autopilot that did not answer the last one.
    link.streams_requested(0.6)
    assert link.wants_set_up(0.6)
    link.setting_up()
    # An outage ends the contact: the next one is set up again, streams or not.
    assert link.update(5.0) == "outage"
    assert not link.wants_set_up(5.0)  # no heartbeat: nobody to set up
    link.heard(6.0)
    link.position(6.0)
    link.status(6.0)
    assert link.update(6.0) == "recovered" and link.wants_set_up(6.0)
