"""The drone's pure core beyond the Sequencer: sightings, who is lost, what a request may
carry, which failures are booked (no sockets, no clock: every time is an argument)."""

from __future__ import annotations

import grpc
import pytest

from baton.digest import request_digest
from baton.drone.core import RESTART_GRACE_S, START_GRACE_S, DroneCore
from baton.drone.policy import Station
from baton.drone.safety import (
    CONFIGURED,
    FROM_AUTOPILOT,
    Bound,
    Failsafe,
    SafetyParams,
    VehicleLimits,
    gcs_failsafe_params,
    landing_due,
    limit_params,
    limit_refusal,
    nearest_station,
    sleep_refusal,
    vehicle_limits,
)
from baton.drone.sequencer import Sequencer
from baton.drone.store import Intent
from baton.rpc.errors import StatusError
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2

GET = "/baton.v1.Mobility/GetPosition"
GOTO = "/baton.v1.Mobility/Goto"
RPC = drone_pb2.HANDOVER_TRIGGER_RPC


def core(takeover_after_s: float = 1.0, prepare_timeout_s: float = 4.0) -> DroneCore:
    """Ring 0 -> 1 -> 2, master 0: lost after 1 s unseen, or 4 s without serving."""
    seq = Sequencer([0, 1, 2], initial_master=0, prepare_timeout_s=prepare_timeout_s)
    return DroneCore(seq, takeover_after_s)


def request(reqnr: int, cid: int = 0, epoch: int = 1) -> drone_pb2.InvokeRequest:
    return drone_pb2.InvokeRequest(controller_id=cid, epoch=epoch, reqnr=reqnr, method=GET)


def test_a_master_that_holds_a_standby_stream_but_never_serves_is_lost() -> None:
    """Made master cooperatively, 1 keeps its standby stream (seen every turn) but neither
    connects nor sends a request: lost once it has not served for the longer of the
    takeover time and the prepare timeout since the switch; 2 takes over."""
    drone = core()
    assert drone.serve_within_s == 4.0
    assert drone.takeover_due(0.0, {0, 1, 2}, {0}, None) is None
    drone.seq.switch(1, RPC, 10.0)
    assert drone.takeover_due(13.9, {0, 1, 2}, set(), None) is None
    due = drone.takeover_due(14.0, {0, 1, 2}, set(), None)
    assert due is not None and (due.new_master, due.lost, due.lost_at) == (2, 1, 10.0)


def test_a_master_serves_while_it_holds_its_connect_stream_or_sends_requests() -> None:
    drone = core()
    drone.seq.switch(1, RPC, 10.0)
    assert drone.takeover_due(12.0, {0, 1, 2}, {1}, None) is None  # connected at 12
    assert drone.takeover_due(15.9, {0, 1, 2}, set(), None) is None
    drone.admit(request(1, cid=1, epoch=2), request_digest(GET, b""), 15.0)  # a request
    assert drone.takeover_due(18.9, {0, 1, 2}, set(), None) is None
    due = drone.takeover_due(19.0, {0, 1, 2}, set(), None)
    assert due is not None and (due.new_master, due.lost) == (2, 1)


def test_a_master_not_serving_with_nobody_else_reachable_is_not_taken_over() -> None:
    drone = core()
    drone.seq.switch(1, RPC, 10.0)
    assert drone.takeover_due(3.0, {0, 1, 2}, {0}, None) is None
    drone.seen(0, 29.5)  # the old master, seen as its stream ended: not lost yet
    assert drone.takeover_due(30.0, {1}, set(), None) is None
    # With a handover policy, only a controller in range may take over.
    assert drone.takeover_due(30.0, {0, 1, 2}, set(), {1, 0}) is not None
    due = drone.takeover_due(30.0, {0, 1, 2}, set(), {1, 0})
    assert due is not None and due.new_master == 0


def test_a_master_never_seen_counts_from_the_end_of_the_start_up_grace() -> None:
    drone = core(prepare_timeout_s=1.0)
    assert drone.takeover_due(0.0, {1, 2}, set(), None) is None  # first sighting at 0
    assert drone.unseen_from == START_GRACE_S
    assert drone.takeover_due(START_GRACE_S + 0.9, {1, 2}, set(), None) is None
    due = drone.takeover_due(START_GRACE_S + 1.0, {1, 2}, set(), None)
    assert due is not None and (due.new_master, due.lost) == (1, 0)


def test_no_takeover_time_means_never() -> None:
    drone = core(takeover_after_s=0.0)
    drone.seq.switch(1, RPC, 10.0)
    assert drone.serve_within_s == 0.0
    assert drone.takeover_due(1e6, {0, 2}, set(), None) is None


def test_a_resumed_master_gets_the_restart_grace() -> None:
    drone = core()
    handover = drone_pb2.HandoverRecord(old_master=0, new_master=1, epoch=2, decided_at=1.0)
    drone.resume(100.0, 1, [handover], (5, 5, 0, 0), [], [], [], 0)
    assert drone.last_seen[1] == drone.last_served[1] == 100.0 + RESTART_GRACE_S
    assert drone.takeover_due(100.0 + RESTART_GRACE_S + 0.9, {0, 2}, set(), None) is None
    due = drone.takeover_due(100.0 + RESTART_GRACE_S + 1.0, {0, 2}, set(), None)
    assert due is not None and (due.new_master, due.lost) == (2, 1)


def test_master_answers_hold_only_what_a_controller_answers_itself() -> None:
    drone = core()
    clock = drone_pb2.RetainedReply(reqnr=1, method="/baton.v1.Clock/Now")
    gave_up = drone_pb2.RetainedReply(reqnr=2, method=GOTO, given_up=True)
    assert [kept.reqnr for kept in drone.master_answers(3, [clock, gave_up])] == [1, 2]
    for bad in (
        drone_pb2.RetainedReply(reqnr=2, method=GOTO),  # a drone call not given up
        drone_pb2.RetainedReply(reqnr=2, method="/baton.v1.Nothing/Here"),
    ):
        with pytest.raises(StatusError) as info:
            drone.master_answers(3, [bad])
        assert info.value.code is grpc.StatusCode.INVALID_ARGUMENT
        assert "master_answers holds reqnr 2" in info.value.message
    # Refused before admission: nothing changes.
    bad_request = request(1)
    bad_request.master_answers.append(drone_pb2.RetainedReply(reqnr=1, method=GOTO))
    with pytest.raises(StatusError):
        drone.admit(bad_request, request_digest(GET, b""), 1.0)
    assert drone.seq.last_reqnr == 0


def test_every_failure_is_booked_but_unavailable() -> None:
    assert not DroneCore.books(StatusError(grpc.StatusCode.UNAVAILABLE, "no vehicle"))
    for code in (grpc.StatusCode.DEADLINE_EXCEEDED, grpc.StatusCode.INVALID_ARGUMENT):
        assert DroneCore.books(StatusError(code, "failed after admission"))


def test_a_read_cut_off_runs_again_and_a_command_cut_off_is_booked() -> None:
    drone = core()
    assert drone.cut_off(Intent(4, GET, b"", 0, 1.0)) is None
    error = drone.cut_off(Intent(4, GOTO, b"", 0, 1.0))
    assert error is not None and error.code is grpc.StatusCode.UNKNOWN


def test_a_masters_connect_carries_the_grant_then_the_retained_replies_in_batches() -> None:
    drone = core()
    digest = request_digest(GET, b"")
    for reqnr in (1, 2, 3):
        drone.seq.admit(0, 1, reqnr, GET, digest)
        drone.seq.served(0, reqnr, GET, digest, b"x" * 40, float(reqnr), float(reqnr))
    not_master = drone_pb2.ConnectRequest(controller_id=1)
    assert drone.connected(not_master) is None  # not the master: nothing but a notice owed
    first = drone.connected(
        drone_pb2.ConnectRequest(controller_id=0, holds_reqnr=1), batch_bytes=64
    )
    assert first is not None
    grant, batches = first
    assert (grant.master, grant.epoch, grant.last_reqnr, grant.retained_through) == (0, 1, 3, 3)
    assert [[reply.reqnr for reply in batch] for batch in batches] == [[2], [3]]


def test_a_connect_stream_carries_a_preparation_once_then_the_notice() -> None:
    drone = core()
    assert drone.stream_event(0, None) is None
    notice = drone.seq.prepare(1, RPC, 1.0)
    assert drone.stream_event(0, None) is notice
    assert drone.stream_event(0, notice) is None  # sent already
    drone.seq.switch(2, RPC, 2.0)
    owed = drone.stream_event(0, notice)
    assert isinstance(owed, drone_pb2.HandoverNotice) and owed.new_master == 2


# -- the safety net (drone/safety.py) ---------------------------------------------

SET_SPEED = "/baton.v1.Mobility/SetSpeed"


def safe_core(lost_link_s: float = 10.0, action: str = "rtl") -> DroneCore:
    seq = Sequencer([0, 1, 2], initial_master=0)
    params = SafetyParams(lost_link_s, action, max_speed_m_s=15.0, max_altitude_m=120.0)
    return DroneCore(seq, 1.0, params)


def test_no_usable_controller_for_lost_link_s_in_the_air_is_a_failsafe() -> None:
    drone = safe_core()
    assert drone.failsafe_due(0.0, {0, 1}, None, airborne=True) is None
    assert drone.failsafe_due(9.9, set(), None, airborne=True) is None
    due = drone.failsafe_due(10.0, set(), None, airborne=True)
    assert due is not None and (due.cause, due.action, due.since) == ("lost_link", "rtl", 10.0)
    assert "no usable controller for 10.0 s" in due.reason


def test_a_request_or_a_stream_of_any_controller_keeps_the_link_usable() -> None:
    drone = safe_core()
    assert drone.failsafe_due(0.0, set(), None, airborne=True) is None
    drone.seen(2, 8.0)  # a request, or a stream that ended
    assert drone.failsafe_due(17.9, set(), None, airborne=True) is None
    assert drone.failsafe_due(18.0, set(), None, airborne=True) is not None


def test_on_the_ground_no_failsafe_and_the_time_counts_from_the_last_look_there() -> None:
    drone = safe_core()
    assert drone.failsafe_due(0.0, set(), None, airborne=False) is None
    assert drone.failsafe_due(100.0, set(), None, airborne=False) is None
    assert drone.failsafe_due(100.1, set(), None, airborne=True) is None
    assert drone.failsafe_due(109.9, set(), None, airborne=True) is None
    assert drone.failsafe_due(110.0, set(), None, airborne=True) is not None


def test_controllers_out_of_range_are_not_usable_with_a_policy() -> None:
    """1 holds a stream but is out of range: the link was last usable at 0 (0 in range)."""
    drone = safe_core()
    assert drone.failsafe_due(0.0, {0}, None, airborne=True) is None
    assert drone.failsafe_due(10.0, {1}, set(), airborne=True) is not None


def test_lost_link_off_never_fails_safe() -> None:
    drone = safe_core(lost_link_s=0.0)
    assert drone.failsafe_due(0.0, set(), None, airborne=True) is None
    assert drone.failsafe_due(1e6, set(), None, airborne=True) is None


def test_nearest_station_flies_to_the_station_given_else_home() -> None:
    due = safe_core(action="nearest_station").failsafe_due(0.0, set(), None, True, nearest=2)
    assert due is None
    drone = safe_core(action="nearest_station")
    drone.failsafe_due(0.0, set(), None, True, nearest=2)
    due = drone.failsafe_due(10.0, set(), None, True, nearest=2)
    assert due is not None and (due.action, due.station) == ("nearest_station", 2)
    drone = safe_core(action="nearest_station")
    drone.failsafe_due(0.0, set(), None, True)
    due = drone.failsafe_due(10.0, set(), None, True, nearest=None)
    assert due is not None and (due.action, due.station) == ("rtl", None)


def test_in_failsafe_every_request_is_refused_before_execution_and_booked() -> None:
    """Admitted (its number used, a duplicate answered from the cache) but refused
    FAILED_PRECONDITION, until an operator resumes."""
    drone = safe_core()
    drone.failsafe_due(0.0, set(), None, True)
    due = drone.failsafe_due(10.0, set(), None, True)
    assert due is not None
    drone.enter_failsafe(due)
    assert drone.failsafe_due(30.0, set(), None, True) is None  # once
    admitted = drone.admit(request(1), request_digest(GET, b""), 31.0)
    assert admitted.cached is None and admitted.refused is not None
    assert admitted.refused.code is grpc.StatusCode.FAILED_PRECONDITION
    assert "in failsafe (lost_link" in admitted.refused.message
    assert "Resume" in admitted.refused.message
    cleared, taken = drone.resume_mission(40.0)
    assert cleared is due and taken.command == "resume"
    with pytest.raises(StatusError, match="neither paused nor in failsafe"):
        drone.resume_mission(40.0)
    drone.seq.served(0, 1, GET, request_digest(GET, b""), b"", 31.0, 31.0, admitted.refused)
    assert drone.admit(request(2), request_digest(GET, b""), 41.0).refused is None
    # the lost-link time counts afresh from the resume
    assert drone.failsafe_due(49.9, set(), None, True) is None


def test_a_set_speed_beyond_the_vehicle_s_bound_is_refused_naming_it() -> None:
    drone = safe_core()
    payload = api.SetSpeedRequest(speed_m_s=1e9).SerializeToString()
    call = drone_pb2.InvokeRequest(
        controller_id=0, epoch=1, reqnr=1, method=SET_SPEED, payload=payload
    )
    refused = drone.admit(call, request_digest(SET_SPEED, payload), 0.0).refused
    assert refused is not None and refused.code is grpc.StatusCode.INVALID_ARGUMENT
    assert "safety.max_speed = 15" in refused.message and "1e+09" in refused.message
    ok = api.SetSpeedRequest(speed_m_s=15.0).SerializeToString()
    assert drone.refusal(SET_SPEED, ok) is None


def test_limits_of_altitude_and_sleep() -> None:
    params = SafetyParams(max_altitude_m=120.0)
    high = api.GotoRequest(latitude_deg=1, longitude_deg=1, relative_altitude_m=121)
    refused = limit_refusal("Mobility.Goto", high, params)
    assert refused is not None and "safety.max_altitude = 120" in refused.message
    assert limit_refusal("Mobility.Takeoff", api.TakeoffRequest(altitude_m=120), params) is None
    too_long = sleep_refusal(1e12, 600.0)
    assert too_long is not None and too_long.code is grpc.StatusCode.INVALID_ARGUMENT
    assert "safety.max_sleep = 600" in too_long.message
    assert sleep_refusal(600.0, 600.0) is None


SET_SPEED_AT = "Mobility.SetSpeed"


def speed_refusal(speed_m_s: float, params: SafetyParams, vehicle: VehicleLimits) -> str | None:
    refused = limit_refusal(SET_SPEED_AT, api.SetSpeedRequest(speed_m_s=speed_m_s), params, vehicle)
    assert refused is None or refused.code is grpc.StatusCode.INVALID_ARGUMENT
    return None if refused is None else refused.message


def test_the_speed_bound_is_the_configured_one_the_vehicle_s_or_the_smaller() -> None:
    configured, unbounded = SafetyParams(max_speed_m_s=15.0), SafetyParams()
    says_12 = VehicleLimits(speed_m_s=12.0, speed_param="MPC_XY_VEL_MAX")
    says_none = VehicleLimits()
    # configured only
    assert speed_refusal(15.0, configured, says_none) is None
    assert speed_refusal(16.0, configured, says_none) == (
        "Mobility.SetSpeed: speed_m_s 16 is beyond the bound safety.max_speed = 15; "
        "nothing was executed"
    )
    # the vehicle's only
    assert speed_refusal(12.0, unbounded, says_12) is None
    assert speed_refusal(30.0, unbounded, says_12) == (
        "Mobility.SetSpeed: speed_m_s 30 is beyond the vehicle's bound MPC_XY_VEL_MAX = 12 "
        "(read from the autopilot); nothing was executed"
    )
    # both: the smaller wins, whichever it is
    assert "MPC_XY_VEL_MAX = 12" in (speed_refusal(13.0, configured, says_12) or "")
    says_20 = VehicleLimits(speed_m_s=20.0, speed_param="MPC_XY_VEL_MAX")
    assert "safety.max_speed = 15" in (speed_refusal(16.0, configured, says_20) or "")
    # neither: nothing is refused
    assert speed_refusal(1e9, unbounded, says_none) is None


def test_the_altitude_bound_names_the_autopilot_s_ceiling_when_it_is_smaller() -> None:
    params = SafetyParams(max_altitude_m=120.0)
    ceiling = VehicleLimits(altitude_m=60.0, altitude_param="GF_MAX_VER_DIST")
    goto = api.GotoRequest(latitude_deg=1, longitude_deg=1, relative_altitude_m=61)
    refused = limit_refusal("Mobility.Goto", goto, params, ceiling)
    assert refused is not None and "relative_altitude_m 61" in refused.message
    assert "the vehicle's bound GF_MAX_VER_DIST = 60 (read from the autopilot)" in refused.message
    takeoff = api.TakeoffRequest(altitude_m=60)
    assert limit_refusal("Mobility.Takeoff", takeoff, params, ceiling) is None


def test_the_core_refuses_beyond_what_the_autopilot_said_and_shows_the_bounds() -> None:
    drone = safe_core()
    fast = api.SetSpeedRequest(speed_m_s=14.0).SerializeToString()
    assert drone.refusal(SET_SPEED, fast) is None
    assert drone.bounds()[0] == Bound(15.0, "safety.max_speed", CONFIGURED)
    drone.limits_read(VehicleLimits(speed_m_s=10.0, speed_param="MPC_XY_VEL_MAX"))
    refused = drone.refusal(SET_SPEED, fast)
    assert refused is not None and "MPC_XY_VEL_MAX = 10" in refused.message
    speed, altitude = drone.bounds()
    assert speed == Bound(10.0, "MPC_XY_VEL_MAX", FROM_AUTOPILOT)
    assert altitude == Bound(120.0, "safety.max_altitude", CONFIGURED)


def test_the_autopilot_s_bounds_from_its_parameters() -> None:
    # PX4: its horizontal maximum and its geofence ceiling (0: none)
    px4 = vehicle_limits(False, {"MPC_XY_VEL_MAX": 12.0, "GF_MAX_VER_DIST": 0.0})
    assert px4 == VehicleLimits(12.0, "MPC_XY_VEL_MAX")
    assert vehicle_limits(False, {"GF_MAX_VER_DIST": 80.0}).altitude_param == "GF_MAX_VER_DIST"
    # a parameter the autopilot lacks is absent: no bound from it
    assert vehicle_limits(False, {}) == VehicleLimits()
    # ArduPilot: FENCE_ALT_MAX only where the fence is on with its altitude bit
    on = {"FENCE_ENABLE": 1.0, "FENCE_TYPE": 7.0, "FENCE_ALT_MAX": 100.0}
    assert vehicle_limits(True, on) == VehicleLimits(
        altitude_m=100.0, altitude_param="FENCE_ALT_MAX"
    )
    assert vehicle_limits(True, {**on, "FENCE_ENABLE": 0.0}) == VehicleLimits()
    assert vehicle_limits(True, {**on, "FENCE_TYPE": 6.0}) == VehicleLimits()
    # ArduPilot says no horizontal maximum (WPNAV_SPEED is a default): none is read
    assert [p.name for p in limit_params(True, own_ceiling=False)] == [
        "FENCE_ENABLE",
        "FENCE_TYPE",
        "FENCE_ALT_MAX",
    ]
    # the ceiling the drone's own fence sets is not read back as the vehicle's
    assert limit_params(True, own_ceiling=True) == []
    assert [p.name for p in limit_params(False, own_ceiling=True)] == ["MPC_XY_VEL_MAX"]


def test_nearest_station_and_landing_over_it() -> None:
    from baton.sdk.types import Position

    stations = {
        0: Station(0, Position(47.0, 8.0), 0.0),
        1: Station(1, Position(47.01, 8.0), 0.0),
    }
    assert nearest_station(api.Position(latitude_deg=47.008, longitude_deg=8.0), stations) == 1
    assert nearest_station(api.Position(), stations) is None
    assert landing_due(api.Position(latitude_deg=47.01, longitude_deg=8.0), stations[1])
    assert not landing_due(api.Position(latitude_deg=47.0099, longitude_deg=8.0), stations[1])


def test_the_autopilot_s_own_gcs_failsafe_parameters() -> None:
    ardupilot = gcs_failsafe_params(True, 10.0, 245)
    assert [(p.name, p.value) for p in ardupilot] == [
        ("SYSID_MYGCS", 245),
        ("FS_GCS_TIMEOUT", 10.0),
        ("FS_GCS_ENABLE", 1),
    ]
    px4 = gcs_failsafe_params(False, 2.5, 245)
    assert [(p.name, p.value) for p in px4] == [("COM_DL_LOSS_T", 5), ("NAV_DLL_ACT", 2)]
    assert gcs_failsafe_params(True, 0.0, 245) == []


def test_below_the_battery_reserve_the_mission_ends_once() -> None:
    seq = Sequencer([0, 1, 2], initial_master=0)
    drone = DroneCore(seq, 1.0, SafetyParams(10.0, "hold", battery_reserve_pct=25.0))
    assert drone.battery_due(0.0, 25.0, airborne=True) is None
    assert drone.battery_due(0.0, float("nan"), airborne=True) is None  # not said
    assert drone.battery_due(0.0, 20.0, airborne=False) is None  # on the ground
    due = drone.battery_due(1.0, 24.9, airborne=True)
    assert due is not None and (due.cause, due.action) == ("battery", "rtl")
    assert "battery 24.9 % below the reserve of 25 %" in due.reason
    drone.enter_failsafe(due)
    assert drone.battery_due(2.0, 20.0, airborne=True) is None  # once
    refused = drone.refusal(GET, b"")
    assert refused is not None and "in failsafe (battery" in refused.message


def test_a_low_battery_ends_a_lost_link_hold_but_not_a_return() -> None:
    seq = Sequencer([0, 1, 2], initial_master=0)
    params = SafetyParams(10.0, "hold", battery_reserve_pct=25.0, battery_action="land")
    drone = DroneCore(seq, 1.0, params)
    drone.failsafe_due(0.0, set(), None, True)
    held = drone.failsafe_due(10.0, set(), None, True)
    assert held is not None and held.action == "hold"
    drone.enter_failsafe(held)
    low = drone.battery_due(11.0, 20.0, airborne=True)
    assert low is not None and low.action == "land"
    returning = DroneCore(Sequencer([0], initial_master=0), 1.0, SafetyParams(10.0, "rtl", 0, 0))
    returning.enter_failsafe(Failsafe("lost_link", "rtl", 0.0, "gone"))
    assert returning.battery_due(1.0, 1.0, airborne=True) is None
    # nearest_station without a known station: home
    near = DroneCore(
        seq, 1.0, SafetyParams(battery_reserve_pct=25.0, battery_action="nearest_station")
    )
    due = near.battery_due(0.0, 20.0, True, nearest=None)
    assert due is not None and due.action == "rtl" and "no station known" in due.reason


def test_a_taker_holding_a_framing_a_takeover_replaced_is_told_so_by_its_grant() -> None:
    """--policy predictive 19072: the drone granted the takeover of epoch 3 to a taker
    whose top message (15, of epoch 1) an earlier taker (epoch 2, framing after message
    12) had numbered otherwise. Its Connected now says from which number and by which
    epoch, and the drone does not take that holding for the log the taker builds on
    (``taker_lognr``); a taker on the ring's framing is granted as before."""
    drone = core()
    digest = request_digest(GET, b"")
    drone.seq.admit(0, 1, 1, GET, digest)
    drone.seq.served(0, 1, GET, digest, b"x", 1.0, 1.0)
    drone.seq.switch(1, drone_pb2.HANDOVER_TRIGGER_LOST, now=4.0, takeover=True, lost_at=1.0)
    framing = request(2, cid=1, epoch=2)
    framing.framed_after_lognr, framing.framed_after_epoch = 12, 1
    drone.admit(framing, digest, received_at=5.0)
    drone.seq.switch(2, drone_pb2.HANDOVER_TRIGGER_LOST, now=6.0, takeover=True, lost_at=5.0)
    replaced = drone_pb2.ConnectRequest(controller_id=2, holds_lognr=15, holds_lognr_epoch=1)
    said = drone.connected(replaced)
    assert said is not None
    assert (said[0].replaced_from_lognr, said[0].replaced_by_epoch) == (13, 2)
    assert not drone.seq.handovers[-1].taker_lognr_epoch
    ours = drone_pb2.ConnectRequest(controller_id=2, holds_lognr=13, holds_lognr_epoch=2)
    said = drone.connected(ours)
    assert said is not None and not said[0].replaced_from_lognr
    assert drone.seq.handovers[-1].taker_lognr == 13


def test_a_framing_said_to_follow_a_newer_mastership_is_refused_and_admits_nothing() -> None:
    """``framed_after_epoch`` newer than the request's own epoch cannot be: INVALID_ARGUMENT
    naming both, before anything is admitted or kept on the record."""
    drone = core()
    digest = request_digest(GET, b"")
    bad = request(1)
    bad.framed_after_lognr, bad.framed_after_epoch = 3, 2
    with pytest.raises(StatusError) as info:
        drone.admit(bad, digest, received_at=1.0)
    assert info.value.code is grpc.StatusCode.INVALID_ARGUMENT
    assert "framed_after_epoch 2 is newer than the request's epoch 1" in info.value.message
    assert drone.seq.last_reqnr == 0
