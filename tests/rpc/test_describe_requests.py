"""Requests shown to a person decode their fields, as ``baton replay`` shows them: the
determinism guard's message is built by ``describe_nondeterminism``."""

from __future__ import annotations

from baton.controller.protocol import NonDeterminismError
from baton.rpc.methods import describe_nondeterminism, describe_request, path
from baton.v1 import drone_api_pb2, ring_pb2

TAKEOFF = path("Mobility.Takeoff")
LAND = path("Mobility.Land")


def takeoff(altitude_m: float) -> bytes:
    return drone_api_pb2.TakeoffRequest(altitude_m=altitude_m).SerializeToString()


def test_a_request_is_shown_as_its_fields() -> None:
    assert describe_request(TAKEOFF, takeoff(10)) == "Mobility.Takeoff {altitude_m: 10.0}"


def test_a_request_that_does_not_decode_is_shown_as_bytes() -> None:
    assert (
        describe_request(TAKEOFF, b"\xff") == "Mobility.Takeoff (does not decode) request bytes ff"
    )


def test_the_guards_message_decodes_both_requests_and_names_the_fields() -> None:
    message = describe_nondeterminism(5, TAKEOFF, takeoff(10), TAKEOFF, takeoff(15))
    assert message == (
        "non-deterministic mission program at request 5: the log holds "
        "Mobility.Takeoff {altitude_m: 10.0} but this program asks "
        "Mobility.Takeoff {altitude_m: 15.0} (fields that differ: altitude_m)"
    )


def test_another_method_is_shown_without_fields_that_differ() -> None:
    land = drone_api_pb2.LandRequest().SerializeToString()
    message = describe_nondeterminism(7, TAKEOFF, takeoff(10), LAND, land)
    assert message.endswith(
        "the log holds Mobility.Takeoff {altitude_m: 10.0} but this program asks Mobility.Land {}"
    )


def test_the_determinism_guard_raises_with_the_decoded_message() -> None:
    logged = ring_pb2.LogEntry(reqnr=5, method=TAKEOFF, request=takeoff(10))
    error = NonDeterminismError(5, logged, TAKEOFF, takeoff(15))
    assert str(error) == describe_nondeterminism(5, TAKEOFF, takeoff(10), TAKEOFF, takeoff(15))
