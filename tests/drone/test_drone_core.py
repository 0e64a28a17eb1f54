"""The drone's pure core beyond the Sequencer: sightings, who is lost, what a request may
carry, which failures are booked (no sockets, no clock: every time is an argument)."""

from __future__ import annotations

import grpc
import pytest

from baton.digest import request_digest
from baton.drone.core import RESTART_GRACE_S, START_GRACE_S, DroneCore
from baton.drone.sequencer import Sequencer
from baton.drone.store import Intent
from baton.rpc.errors import StatusError
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
    assert drone.connected(1, 0) is None  # not the master: nothing but a notice owed
    first = drone.connected(0, holds_reqnr=1, batch_bytes=64)
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
