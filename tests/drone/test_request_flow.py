"""A request's flow on the drone (request_flow.RequestFlow), driven by hand: the turns both
the service and the simulation run."""

from __future__ import annotations

import grpc
import pytest

from baton.digest import request_digest
from baton.drone.core import DroneCore
from baton.drone.effects import Book
from baton.drone.request_flow import (
    Acknowledged,
    Begin,
    Booking,
    Duplicate,
    Execute,
    Executed,
    Failed,
    Flow,
    LookAtVehicle,
    Now,
    Outcome,
    Parse,
    Replied,
    RequestFlow,
    Send,
    VehicleSeen,
)
from baton.drone.safety import Failsafe
from baton.drone.sequencer import Sequencer
from baton.rpc.errors import StatusError
from baton.v1 import drone_pb2

GET = "/baton.v1.Mobility/GetPosition"
LAND = "/baton.v1.Mobility/Land"


def core() -> DroneCore:
    """Ring 0 -> 1 -> 2, master 0."""
    return DroneCore(Sequencer([0, 1, 2], initial_master=0), 1.0)


def request(reqnr: int, method: str = GET) -> drone_pb2.InvokeRequest:
    return drone_pb2.InvokeRequest(controller_id=0, epoch=1, reqnr=reqnr, method=method)


def drive(steps: Flow, answers: dict[type[object], object]) -> tuple[list[type], Outcome]:
    """Runs ``steps``, answering each turn of a kind with ``answers[kind]`` (else None):
    the kinds of turns taken, and the outcome."""
    taken: list[type] = []
    result: object = None
    while True:
        try:
            io = steps.send(result)
        except StopIteration as stop:
            return taken, stop.value
        taken.append(type(io))
        result = answers.get(type(io))


def test_a_request_is_stored_before_it_executes_and_booked_before_it_is_answered() -> None:
    drone = core()
    answers = {
        LookAtVehicle: VehicleSeen(True, ""),
        Send: 1.0,
        Executed: None,
        Execute: Executed(1.5, b"here"),
        Now: 1.6,
    }
    taken, outcome = drive(RequestFlow(drone, request(1), 0.9).run(), answers)
    assert taken == [Begin, Parse, LookAtVehicle, Send, Execute, Acknowledged, Now, Booking]
    assert outcome == Replied(b"here", 1, request_digest(GET, b""))
    assert drone.seq.last_reqnr == 1
    # Sent again, it is answered from the cache: nothing executes twice.
    again, duplicate = drive(RequestFlow(drone, request(1), 2.0).run(), answers)
    assert again == [] and isinstance(duplicate, Duplicate)


def test_a_vehicle_that_is_not_there_executes_nothing_and_leaves_the_number_unused() -> None:
    drone = core()
    steps = RequestFlow(drone, request(1), 0.0).run()
    answers = {LookAtVehicle: VehicleSeen(False, "(an outage)"), Now: 0.1}
    taken, outcome = drive(steps, answers)
    assert Send not in taken and Execute not in taken
    assert isinstance(outcome, Failed) and not outcome.booked
    assert outcome.error.code is grpc.StatusCode.UNAVAILABLE
    assert drone.seq.last_reqnr == 0  # the same request may be sent again


def test_a_request_refused_after_admission_is_booked_and_never_reaches_the_vehicle() -> None:
    drone = core()
    drone.enter_failsafe(Failsafe("lost_link", "rtl", 0.0, "gone"))
    booked: list[Booking] = []
    steps = RequestFlow(drone, request(1, LAND), 0.0).run()
    result: object = None
    while True:
        try:
            io = steps.send(result)
        except StopIteration as stop:
            outcome = stop.value
            break
        if isinstance(io, Booking):
            booked.append(io)
        assert not isinstance(io, Parse | Send | Execute)
        result = 0.1 if isinstance(io, Now) else None
    assert isinstance(outcome, Failed) and outcome.booked
    assert [type(e) for e in booked[0].effects][:1] == [Book]
    assert drone.seq.last_reqnr == 1


def test_a_payload_that_does_not_parse_is_booked_as_its_failure() -> None:
    drone = core()
    bad = StatusError(grpc.StatusCode.INVALID_ARGUMENT, "does not parse")
    taken, outcome = drive(RequestFlow(drone, request(1), 0.0).run(), {Parse: bad, Now: 0.1})
    assert taken == [Begin, Parse, Now, Booking]
    assert outcome == Failed(bad, True)


def test_a_refusal_at_admission_leaves_the_first_turn_and_stores_nothing() -> None:
    drone = core()
    not_master = drone_pb2.InvokeRequest(controller_id=1, epoch=1, reqnr=1, method=GET)
    with pytest.raises(StatusError) as refused:
        next(RequestFlow(drone, not_master, 0.0).run())
    assert refused.value.code is grpc.StatusCode.FAILED_PRECONDITION
    assert drone.seq.last_reqnr == 0
