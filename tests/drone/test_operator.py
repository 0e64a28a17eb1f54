"""An operator's commands as pure decisions (drone/operator.py, held by DroneCore): fed
requests and commands at chosen times, no sockets, no clock (issue 32, item 4)."""

from __future__ import annotations

import grpc
import pytest

from baton.digest import request_digest
from baton.drone.core import DroneCore
from baton.drone.operator import KEPT, Operator
from baton.drone.safety import Failsafe
from baton.drone.sequencer import Sequencer
from baton.rpc.errors import StatusError
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2

GET = "/baton.v1.Mobility/GetPosition"
GOTO = "/baton.v1.Mobility/Goto"
DIGEST = request_digest(GET, b"")


def core() -> DroneCore:
    """Ring 0 -> 1, master 0."""
    return DroneCore(Sequencer([0, 1], initial_master=0), 1.0)


def request(reqnr: int, cid: int = 0) -> drone_pb2.InvokeRequest:
    return drone_pb2.InvokeRequest(controller_id=cid, epoch=1, reqnr=reqnr, method=GET)


def serve(drone: DroneCore, reqnr: int) -> None:
    """Request ``reqnr`` admitted and served, as a driver does."""
    admitted = drone.admit(request(reqnr), DIGEST, float(reqnr))
    assert admitted.cached is None and admitted.refused is None
    drone.seq.served(0, reqnr, GET, DIGEST, b"here", float(reqnr), float(reqnr))


def test_paused_the_masters_next_request_waits_and_a_served_one_is_answered_again() -> None:
    drone = core()
    serve(drone, 1)
    taken = drone.operator.pause(10.0, drone.seq.last_reqnr, note="a kite")
    assert (taken.command, taken.action, taken.after_reqnr) == ("pause", "hold", 1)
    assert taken.reason == "paused by the operator after request 1 (a kite)"
    assert drone.holds(request(2))
    assert not drone.holds(request(1))  # served: answered from the cache
    assert not drone.holds(request(2, cid=1))  # not the master: the sequencer refuses it
    assert drone.seq.last_reqnr == 1  # nothing admitted while it waits
    cleared, resumed = drone.resume_mission(12.0)
    assert cleared is None and resumed.command == "resume" and resumed.action == ""
    assert not drone.holds(request(2))
    serve(drone, 2)


def test_a_resume_after_a_pause_mid_leg_flies_the_leg_on() -> None:
    operator = Operator()
    goto = api.GotoRequest(latitude_deg=47.1, longitude_deg=8.2).SerializeToString()
    operator.executed("Goto", goto)
    operator.pause(1.0, 4)
    resumed = operator.resume(2.0, 4, None)
    assert resumed.action == "goto" and operator.leg == goto
    assert "flying on to the last Goto's target" in resumed.reason
    operator.executed("Land", b"")  # a leg ended: nothing to fly on
    operator.pause(3.0, 5)
    assert operator.resume(4.0, 5, None).action == ""


def test_a_resume_clears_a_failsafe_and_the_pause_and_flies_nothing_on() -> None:
    drone = core()
    drone.operator.executed("Goto", b"leg")
    drone.operator.pause(1.0, 0)
    failsafe = Failsafe("lost_link", "rtl", 2.0, "no usable controller for 10 s")
    drone.enter_failsafe(failsafe)
    cleared, taken = drone.resume_mission(3.0)
    assert cleared is failsafe and drone.failsafe is None and drone.operator.paused is None
    assert taken.action == ""  # the failsafe's action stands until the mission's next call
    assert "the pause since request 0 and the lost_link failsafe" in taken.reason


def test_abort_ends_the_mission_every_later_request_refused_and_booked() -> None:
    drone = core()
    serve(drone, 1)
    drone.operator.pause(1.0, 1)
    ended = drone.operator.end("abort", "rtl", 2.0, 1, note="intruder")
    assert drone.operator.paused is None and not drone.holds(request(2))
    assert (ended.command, ended.action) == ("abort", "rtl")
    admitted = drone.admit(request(2), DIGEST, 3.0)
    assert admitted.refused is not None
    assert admitted.refused.code is grpc.StatusCode.FAILED_PRECONDITION
    assert admitted.refused.message == (
        "Mobility.GetPosition: the mission has ended (aborted by the operator after request "
        "1: rtl (intruder)); nothing was executed"
    )
    assert drone.books(admitted.refused)
    for command in (
        lambda: drone.resume_mission(4.0),
        lambda: drone.operator.pause(4.0, 2),
        lambda: drone.operator.end("land_now", "", 4.0, 2),
    ):
        with pytest.raises(StatusError, match="the mission has ended") as refused:
            command()
        assert refused.value.code is grpc.StatusCode.FAILED_PRECONDITION


def test_land_now_lands_and_an_abort_takes_rtl_or_land_only() -> None:
    assert Operator().end("land_now", "rtl", 1.0, 0).action == "land"
    assert Operator().end("abort", "land", 1.0, 0).action == "land"
    with pytest.raises(StatusError, match=r"action 'home' is not one of rtl, land") as bad:
        Operator().end("abort", "home", 1.0, 0)
    assert bad.value.code is grpc.StatusCode.INVALID_ARGUMENT


def test_a_pause_twice_and_a_resume_of_nothing_are_refused_naming_why() -> None:
    operator = Operator()
    with pytest.raises(StatusError, match="neither paused nor in failsafe"):
        operator.resume(1.0, 0, None)
    operator.pause(1.0, 0)
    with pytest.raises(StatusError, match="paused already"):
        operator.pause(2.0, 0)


def test_a_ground_stations_override_pauses_and_leaves_the_vehicle_to_the_station() -> None:
    drone = core()
    taken = drone.operator.pause(1.0, 0, by="ground station 255", note="MAV_CMD_NAV_LAND")
    assert taken.action == "" and taken.by == "ground station 255"
    assert taken.reason == "paused by the ground station 255 after request 0 (MAV_CMD_NAV_LAND)"
    assert drone.holds(request(1))


def test_what_the_vehicle_did_is_recorded_and_the_state_survives_a_restart() -> None:
    operator = Operator()
    operator.executed("Goto", b"\x01leg")
    taken = operator.pause(1.0, 3)
    done = operator.acted(taken, "accepted")
    assert operator.paused is done and operator.commands == [done]
    again = Operator.from_json(operator.to_json())
    assert again == operator
    for i in range(KEPT + 5):
        again.resume(float(i), 3, Failsafe("battery", "rtl", 0.0, "low"))
    assert len(again.commands) == KEPT


def test_the_cli_refuses_an_abort_flag_on_another_command(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from baton.cli import main

    assert main(["operator", "pause", "--land", "--insecure"]) == 2
    assert "--rtl and --land go with abort only" in capsys.readouterr().err


def test_the_cli_says_what_the_drone_took_and_what_the_vehicle_did() -> None:
    from baton.drone.operator_cli import describe

    taken = drone_pb2.OperatorCommand(
        command="abort",
        at=0.0,
        after_reqnr=17,
        action="land",
        reason="aborted by the operator after request 17: land",
        vehicle="accepted",
    )
    assert describe(taken) == (
        "00:00:00 UTC abort: aborted by the operator after request 17: land; the vehicle "
        "told land: accepted"
    )
