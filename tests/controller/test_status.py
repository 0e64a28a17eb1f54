"""A controller's start from its log file and its waiting lines, and what a drone call's
failure means: the pure functions both the runtime's node and the simulation use
(``controller/status.py``, ``controller/invoking.py``)."""

from __future__ import annotations

import grpc
from helpers.protocol import started

from baton.controller.core import ControllerCore, DroneRefusal, Fail, Note
from baton.controller.history import LogHistory
from baton.controller.invoking import RETRY_MAX_S, Sent, failed, replied, retry_pause
from baton.controller.protocol import ControllerProtocol
from baton.controller.status import Sight, holding, recover
from baton.v1 import ring_pb2

POSITION = "/baton.v1.Mobility/GetPosition"


def logged(lognr: int, first_reqnr: int, calls: int = 1) -> ring_pb2.LogMessage:
    entries = [ring_pb2.LogEntry(reqnr=first_reqnr + i, method=POSITION) for i in range(calls)]
    return ring_pb2.LogMessage(lognr=lognr, origin=0, sender=0, epoch=1, entries=entries)


def fresh(cid: int = 1) -> ControllerCore:
    return ControllerCore(ControllerProtocol(cid, [0, 1, 2], 0))


def test_a_restart_believes_its_log_file_and_says_how_far_it_got() -> None:
    history = LogHistory()
    history.add(logged(1, 1, calls=2))
    history.keep_mastership_epoch(1)
    core = fresh()
    (note,) = recover(core, history, 1)
    assert isinstance(note, Note) and note.fields["up_to_lognr"] == 1
    assert (core.protocol.lognr, core.protocol.held_reqnr, core.protocol.epoch) == (1, 2, 1)


def test_a_log_file_the_protocol_refuses_stops_the_mission_with_data_loss() -> None:
    history = LogHistory()
    history.add(logged(1, 5))  # requests 1 to 4 are missing
    (fail,) = recover(fresh(), history, 1)
    assert isinstance(fail, Fail) and fail.code is grpc.StatusCode.DATA_LOSS
    assert "controller 1" in fail.text and "request 5" in fail.text


def test_a_start_with_nothing_believes_nothing() -> None:
    core = fresh()
    assert recover(core, LogHistory(), 1) == [] and core.protocol.lognr == 0


def test_the_waiting_lines_name_what_holds() -> None:
    p = started(0, [0, 1, 2], 0)
    quiet = holding(p, [], Sight(drone=("drone:1", True), successor_link=(True, 0)))
    assert quiet == {}
    sight = Sight(
        drone=("drone:1", False),
        standby_address="drone:1",
        standby_up=False,
        in_flight=(7, POSITION),
        operator_pause="paused by the operator",
        successor_link=(False, 3),
    )
    lines = holding(p, [1], sight)
    assert set(lines) == {"drone", "standby", "paused", "ring", "routed"}
    assert "3 messages not acknowledged" in lines["ring"]
    assert lines["paused"].startswith("request 7")


def test_a_taker_waiting_for_replies_the_drone_let_go_says_so() -> None:
    """A taker granted with the drone's watermark above all it holds, whose predecessor
    holds nothing more, does not say it "handled log message 0 of 0": it says which
    requests it lacks and what would give them."""
    p = started(2, [1, 0, 2], 1)
    p.on_granted(3, takeover=True, watermark_reqnr=7)
    p.on_sync(0)
    assert p.master and not p.caught_up
    line = holding(p, [], Sight())["catch-up"]
    assert "up to request 7 (its watermark at the takeover)" in line, line
    assert "we hold up to request 0" in line and "our predecessor holds no more" in line, line
    assert "log file" in line, line
    unsaid = started(2, [1, 0, 2], 1)
    unsaid.on_granted(3, takeover=True, watermark_reqnr=7)
    unsaid.catch_up_to = None
    assert "controller 0 has not said what it holds" in holding(unsaid, [], Sight())["catch-up"]


def test_a_drone_calls_outcome_follows_its_status() -> None:
    core = ControllerCore(started(0, [0, 1, 2], 0))
    sent = Sent(3, POSITION, b"", b"d", 1)
    reply = replied(sent, b"here", 1, b"sig")
    assert (reply.reqnr, reply.reply, reply.drone_signature) == (3, b"here", b"sig")
    unavailable = failed(core, sent, grpc.StatusCode.UNAVAILABLE, "down", None, 1.0, 60.0, 0)
    assert unavailable.pause is not None and unavailable.entry is None
    late = failed(core, sent, grpc.StatusCode.UNAVAILABLE, "down", None, 60.0, 60.0, 9)
    assert late.entry is not None and late.entry.status_code == grpc.StatusCode.UNAVAILABLE.value[0]
    other = failed(core, sent, grpc.StatusCode.INTERNAL, "boom", None, 0.0, 60.0, 0)
    assert other.entry is not None and other.entry.status_message == "boom"
    refusal = DroneRefusal(master=2, epoch=2, after_reqnr=2)
    refused = failed(core, sent, grpc.StatusCode.FAILED_PRECONDITION, "", refusal, 0.0, 60.0, 0)
    assert refused.entry is None and refused.pause is None and refused.effects


def test_the_retry_pause_doubles_to_its_cap_within_the_limit() -> None:
    assert [retry_pause(n, 0.0, 60.0) for n in range(3)] == [0.2, 0.4, 0.8]
    assert retry_pause(10, 0.0, 60.0) == RETRY_MAX_S
    assert retry_pause(10, 59.5, 60.0) == 0.5
