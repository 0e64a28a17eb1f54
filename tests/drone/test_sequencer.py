"""The drone's pure sequencer: masters, epochs, request order, the script (no sockets)."""

from __future__ import annotations

from dataclasses import replace

import grpc
import pytest

from baton.digest import request_digest
from baton.drone.dedupe import GIVEN_UP, CachedReply
from baton.drone.sequencer import (
    MAX_REQNR_GAP,
    PREPARED_BOUND_BYTES,
    ScriptedHandover,
    Sequencer,
)
from baton.rpc.errors import StatusError
from baton.v1 import drone_pb2

GET = "/baton.v1.Mobility/GetPosition"
DIGEST = request_digest(GET, b"")
SCRIPT, RPC, LOST = (
    drone_pb2.HANDOVER_TRIGGER_SCRIPT,
    drone_pb2.HANDOVER_TRIGGER_RPC,
    drone_pb2.HANDOVER_TRIGGER_LOST,
)


def serve(seq: Sequencer, cid: int, epoch: int, reqnr: int) -> None:
    assert seq.admit(cid, epoch, reqnr, GET, DIGEST) is None
    seq.served(cid, reqnr, GET, DIGEST, b"reply %d" % reqnr, float(reqnr), now=float(reqnr))


def refused(seq: Sequencer, cid: int, epoch: int, reqnr: int) -> StatusError:
    before = (seq.last_reqnr, seq.executed, len(seq.audit))
    with pytest.raises(StatusError) as info:
        seq.admit(cid, epoch, reqnr, GET, DIGEST)
    assert (seq.last_reqnr, seq.executed, len(seq.audit)) == before  # nothing changed
    return info.value


def test_every_switch_grants_the_next_epoch_and_owes_the_old_master_a_notice() -> None:
    seq = Sequencer([0, 1, 2], initial_master=0)
    assert seq.epoch == 1
    serve(seq, 0, 1, 1)
    record = seq.switch(1, RPC, now=5.0)
    assert (record.old_master, record.new_master, record.after_reqnr, record.epoch) == (0, 1, 1, 2)
    notice = seq.pending[0]
    assert (notice.new_master, notice.ended_epoch, notice.epoch) == (1, 1, 2)
    seq.switch(0, RPC, now=6.0)
    assert seq.epoch == 3 and 0 not in seq.pending and seq.pending[1].ended_epoch == 2
    with pytest.raises(StatusError) as same:
        seq.switch(0, RPC, now=7.0)
    assert same.value.code is grpc.StatusCode.FAILED_PRECONDITION


def test_a_request_from_an_earlier_mastership_is_stale_never_executed() -> None:
    """Issue 9, defect 4: a request still on the wire when the role came back."""
    seq = Sequencer([0, 1], initial_master=0)
    serve(seq, 0, 1, 1)
    seq.switch(1, RPC, now=1.0)
    serve(seq, 1, 2, 2)
    seq.switch(0, RPC, now=2.0)  # back to 0, epoch 3
    stale = refused(seq, 0, 1, 2)
    assert stale.code is grpc.StatusCode.FAILED_PRECONDITION and "stale" in stale.message
    assert (
        dict(stale.metadata)["baton-epoch"] == "3" and dict(stale.metadata)["baton-master"] == "0"
    )
    # The same number in the current epoch is answered from the cache.
    cached = seq.admit(0, 3, 2, GET, DIGEST)
    assert cached is not None and cached.reply == b"reply 2"
    serve(seq, 0, 3, 3)


@pytest.mark.parametrize("epoch", [0, 4])
def test_an_epoch_never_granted_is_invalid(epoch: int) -> None:
    seq = Sequencer([0, 1], initial_master=0)
    seq.switch(1, RPC, now=1.0)
    seq.switch(0, RPC, now=2.0)
    assert refused(seq, 0, epoch, 1).code is grpc.StatusCode.INVALID_ARGUMENT


def test_a_non_master_is_refused_before_its_epoch_is_looked_at() -> None:
    seq = Sequencer([0, 1], initial_master=0)
    error = refused(seq, 1, 0, 1)
    assert error.code is grpc.StatusCode.FAILED_PRECONDITION
    assert dict(error.metadata) == {
        "baton-master": "0",
        "baton-epoch": "1",
        "baton-after-reqnr": "0",
    }


def test_request_numbers_increase_by_at_most_the_gap() -> None:
    seq = Sequencer([0], initial_master=0)
    serve(seq, 0, 1, 5)  # 1..4 were the controller's own Clock calls
    assert refused(seq, 0, 1, 4).code is grpc.StatusCode.FAILED_PRECONDITION
    assert refused(seq, 0, 1, 0).code is grpc.StatusCode.INVALID_ARGUMENT
    assert refused(seq, 0, 1, 5 + MAX_REQNR_GAP + 1).code is grpc.StatusCode.FAILED_PRECONDITION
    serve(seq, 0, 1, 5 + MAX_REQNR_GAP)
    other = request_digest("/baton.v1.Mobility/Arm", b"")
    with pytest.raises(StatusError, match="diverged"):
        seq.admit(0, 1, 5, "/baton.v1.Mobility/Arm", other)


def test_the_script_fires_after_the_first_request_at_or_past_its_line() -> None:
    script = {3: ScriptedHandover(3, 1, line=1), 6: ScriptedHandover(6, 1, line=2)}
    seq = Sequencer([0, 1], initial_master=0, script=script)
    serve(seq, 0, 1, 2)
    assert seq.admit(0, 1, 4, GET, DIGEST) is None
    served = seq.served(0, 4, GET, DIGEST, b"", received_at=3.5, now=4.0)
    assert served.handover is not None and served.handover.after_reqnr == 4
    assert (seq.master, seq.epoch, seq.fired_script) == (1, 2, [3])
    assert seq.admit(1, 2, 6, GET, DIGEST) is None
    served = seq.served(1, 6, GET, DIGEST, b"", received_at=6.0, now=6.0)
    assert served.handover is None and served.skipped is not None  # already the master
    first = seq.handovers[0]
    assert first.first_request_at == 0
    assert seq.note_request(1, 9.0) is first and first.delay_s == 5.0


def test_a_lost_master_is_taken_over_by_the_first_reachable_one_after_it_in_ring_order() -> None:
    seq = Sequencer([2, 0, 1], initial_master=0)  # ring 2 -> 0 -> 1 -> 2
    seen = {0: 10.0, 1: 12.0, 2: 12.0}
    assert seq.takeover_due(12.0, {1, 2}, seen, after_s=3.0) is None  # not yet
    due = seq.takeover_due(13.0, {1, 2}, seen, after_s=3.0)
    assert due is not None and (due.new_master, due.lost, due.lost_at) == (1, 0, 10.0)
    due = seq.takeover_due(13.0, {2}, seen, after_s=3.0)  # 1 is gone too: round to 2
    assert due is not None and due.new_master == 2
    assert seq.takeover_due(13.0, set(), seen, after_s=3.0) is None  # nobody to take it
    assert seq.takeover_due(99.0, {1, 2}, seen, after_s=0.0) is None  # turned off
    unseen = {1: 12.0, 2: 12.0}  # the master not seen since the drone started
    assert seq.takeover_due(99.0, {1, 2}, unseen, after_s=3.0) is None
    serve(seq, 0, 1, 1)
    record = seq.switch(1, LOST, now=13.0, takeover=True, lost_at=10.0)
    assert (record.kind, record.epoch, record.lost_at) == (
        drone_pb2.HANDOVER_KIND_TAKEOVER,
        2,
        10.0,
    )
    assert seq.pending[0].takeover
    # The fenced master's requests are refused saying so.
    error = refused(seq, 0, 1, 2)
    assert ("baton-takeover", "1") in error.metadata


def test_a_handover_whose_old_master_dies_before_its_log_left_is_granted_again() -> None:
    seq = Sequencer([0, 1, 2], initial_master=0)
    serve(seq, 0, 1, 1)
    seq.switch(1, SCRIPT, now=20.0)  # cooperative: 1 waits for 0's log
    seen = {0: 20.5, 1: 30.0, 2: 30.0}
    assert seq.takeover_due(23.0, {1, 2}, seen, after_s=3.0) is None
    due = seq.takeover_due(23.5, {1, 2}, seen, after_s=3.0)
    assert due is not None and (due.new_master, due.lost) == (1, 0)
    record = seq.switch(1, LOST, now=23.5, takeover=True, lost_at=due.lost_at)
    assert (record.old_master, record.new_master, record.epoch) == (0, 1, 3)
    assert seq.pending[0].takeover and seq.pending[0].epoch == 3
    # Once the new master has sent a request, a handover is not re-granted.
    seq2 = Sequencer([0, 1], initial_master=0)
    serve(seq2, 0, 1, 1)
    seq2.switch(1, SCRIPT, now=1.0)
    seq2.note_request(1, received_at=1.5)
    assert seq2.takeover_due(9.0, {1}, {0: 1.0, 1: 9.0}, after_s=3.0) is None


def test_two_switches_at_once_whose_first_old_master_dies_are_taken_over() -> None:
    """--lose-master seeds 2407, 2535, 5120, 6027 (F1's pattern): the script hands 0 -> 2,
    an RPC's Handover 2 -> 4 at the same instant, and 0 dies before its log left. 2 never
    goes ACTIVE (it waits for 0's handover message), so it never hands over to 4; the
    last switch's old master (2) is alive. 4 is granted again by takeover of lost 0."""
    seq = Sequencer([0, 4, 1, 2, 3], initial_master=0)
    serve(seq, 0, 1, 1)
    seq.switch(2, SCRIPT, now=20.0)  # epoch 2: 2 waits for 0's log
    seq.switch(4, RPC, now=20.0)  # epoch 3: 4 waits for 2's, which never comes
    seen = {0: 20.5, 1: 30.0, 2: 30.0, 3: 30.0, 4: 30.0}
    live = {1, 2, 3, 4}
    assert seq.takeover_due(23.0, live, seen, after_s=3.0) is None
    due = seq.takeover_due(23.5, live, seen, after_s=3.0)
    assert due is not None and (due.new_master, due.lost, due.lost_at) == (4, 0, 20.5)
    record = seq.switch(4, LOST, now=23.5, takeover=True, lost_at=due.lost_at, lost=due.lost)
    assert (record.old_master, record.new_master, record.epoch) == (0, 4, 4)
    assert seq.pending[0].takeover and seq.pending[0].epoch == 4
    assert seq.taken_over_since(0, 1) is record  # 0's log, if it comes back, is fenced
    assert seq.takeover_due(99.0, live, seen, after_s=3.0) is None  # granted: done
    # A middle master that sent a request held the first one's log: nothing is lost.
    seq2 = Sequencer([0, 1, 2], initial_master=0)
    serve(seq2, 0, 1, 1)
    seq2.switch(1, SCRIPT, now=1.0)
    seq2.note_request(1, received_at=1.5)
    serve(seq2, 1, 2, 2)
    seq2.switch(2, RPC, now=2.0)
    assert seq2.takeover_due(9.0, {1, 2}, {0: 1.0, 1: 9.0, 2: 9.0}, after_s=3.0) is None
    # Nor before a takeover: its taker goes ACTIVE on what it holds, waiting for nobody.
    seq3 = Sequencer([0, 1, 2], initial_master=0)
    serve(seq3, 0, 1, 1)
    seq3.switch(1, LOST, now=1.0, takeover=True)
    seq3.admit_connect(1)
    seq3.switch(2, RPC, now=2.0)
    assert seq3.takeover_due(9.0, {1, 2}, {0: 1.0, 1: 9.0, 2: 9.0}, after_s=3.0) is None


def test_a_handover_from_a_taker_that_has_not_connected_is_a_takeover() -> None:
    """--lose-master seed 1190: the drone handed over cooperatively from a taker that had
    not connected (not ACTIVE): no handover message ever came, the new master waited."""
    seq = Sequencer([0, 1, 2], initial_master=0)
    serve(seq, 0, 1, 1)
    assert not seq.handover_must_take_over(1)  # no takeover yet
    seq.switch(1, LOST, now=5.0, takeover=True, lost_at=1.0)
    assert seq.handover_must_take_over(2)  # 1 was told, but has not connected yet
    assert not seq.handover_must_take_over(1)  # to itself: switch refuses it
    seq.admit_connect(1)
    assert not seq.handover_must_take_over(2)  # connected: cooperative again
    seq.switch(2, RPC, now=6.0)
    assert not seq.handover_must_take_over(0)  # a cooperative grant waits for the log


def test_a_mastership_granted_by_takeover_says_so_after_the_taker_sent_a_request() -> None:
    """--lose-master seed 1092: the taker sent a request, then rejoined with nothing (its
    log had diverged from the ring's). The drone tells a TakeOver only until the taker's
    first request, so its fresh self took the Connected for a cooperative grant and
    waited for ever for a handover message. Every Connected of the mastership says it."""
    seq = Sequencer([0, 1, 2], initial_master=0)
    assert not seq.granted_by_takeover  # the initial grant
    serve(seq, 0, 1, 1)
    seq.switch(1, LOST, now=5.0, takeover=True, lost_at=1.0)
    assert seq.granted_by_takeover
    seq.note_request(1, 6.0)
    serve(seq, 1, 2, 2)
    assert seq.handovers[-1].first_request_at  # no TakeOver is owed any more...
    assert seq.granted_by_takeover  # ...but its Connected says takeover all the same
    seq.switch(2, RPC, now=7.0)
    assert not seq.granted_by_takeover  # cooperative: a handover message is owed


def test_replies_above_the_masters_watermark_are_retained_past_the_window() -> None:
    seq = Sequencer([0, 1], initial_master=0, cache_window=2)
    for reqnr in range(1, 7):
        serve(seq, 0, 1, reqnr)
    assert seq.cache.reqnrs == [1, 2, 3, 4, 5, 6]
    assert seq.admit(0, 1, 7, GET, DIGEST, watermark=4) is None
    assert seq.cache.reqnrs == [5, 6]
    assert seq.admit(0, 1, 7, GET, DIGEST, watermark=99) is None  # capped at what was served
    assert seq.cache.watermark == 6


def test_a_takeover_says_the_watermark_it_was_granted_at_to_the_master_it_fenced() -> None:
    """The takeover's record keeps the drone's watermark then (what the taker must hold);
    the old master's notice and every refusal of its mastership say it, and a later
    rise of the watermark (the taker's own calls) does not change what they say."""
    seq = Sequencer([0, 1, 2], initial_master=0)
    for reqnr in (1, 2, 3):
        serve(seq, 0, 1, reqnr)
    assert seq.admit(0, 1, 4, GET, DIGEST, watermark=2) is None
    record = seq.switch(1, LOST, now=4.0, takeover=True, lost_at=1.0)
    assert record.watermark_reqnr == 2 and seq.pending[0].takeover_watermark_reqnr == 2
    serve(seq, 1, 2, 4)
    assert seq.admit(1, 2, 5, GET, DIGEST, watermark=4) is None
    error = refused(seq, 0, 1, 5)
    assert ("baton-takeover", "1") in error.metadata
    assert ("baton-takeover-watermark", "2") in error.metadata
    cooperative = seq.switch(2, RPC, now=5.0)
    assert cooperative.watermark_reqnr == 0 and not seq.pending[1].takeover_watermark_reqnr


def test_a_takeover_says_the_message_its_taker_built_on_once_it_connected() -> None:
    """The taker's first Connect in its epoch says the log message it handled last; its
    own messages follow that one, and every refusal of the old master's mastership says
    it (``baton-takeover-holds``). A later Connect changes nothing (the taker framed
    messages of its own by then), nor does a Connect of another controller."""
    seq = Sequencer([0, 1, 2], initial_master=0)
    serve(seq, 0, 1, 1)
    seq.switch(1, LOST, now=4.0, takeover=True, lost_at=1.0)
    assert "baton-takeover-holds" not in dict(refused(seq, 0, 1, 2).metadata)
    seq.taker_connected(
        drone_pb2.ConnectRequest(controller_id=2, holds_lognr=9, holds_lognr_epoch=1)
    )
    seq.taker_connected(
        drone_pb2.ConnectRequest(controller_id=1, holds_lognr=3, holds_lognr_epoch=1)
    )
    seq.taker_connected(
        drone_pb2.ConnectRequest(controller_id=1, holds_lognr=5, holds_lognr_epoch=2)
    )
    record = seq.handovers[-1]
    assert (record.taker_lognr, record.taker_lognr_epoch) == (3, 1)
    assert ("baton-takeover-holds", "3/1") in refused(seq, 0, 1, 2).metadata


def test_a_taker_is_given_every_retained_reply_with_the_epoch_that_brought_it() -> None:
    """--policy nearest seed 132: the policy's taker is the nearest station, and may hold
    a framing an earlier takeover replaced. It is given the retained replies it says it
    holds too, each with the epoch of the mastership that brought it, to compare; a
    master granted otherwise only those above what it holds."""
    seq = Sequencer([0, 1, 2], initial_master=0)
    for reqnr in (1, 2, 3):
        serve(seq, 0, 1, reqnr)
    assert seq.admit(0, 1, 4, GET, DIGEST, watermark=1) is None
    assert seq.replies_for_master(holds_reqnr=3) == []  # not a takeover
    seq.switch(1, LOST, now=4.0, takeover=True, lost_at=1.0)
    serve(seq, 1, 2, 4)
    given = [reply.to_proto() for reply in seq.replies_for_master(holds_reqnr=3)]
    assert [(r.reqnr, r.epoch) for r in given] == [(2, 1), (3, 1), (4, 2)]


def test_the_replies_a_taker_says_it_adopted_count_as_brought_in_its_epoch() -> None:
    """--policy nearest seed 4287: master 0's program gave up on request 2, which the
    drone served; 0 handed over to 4 with the give-up (epoch 2), and 4 was taken over by
    1 (epoch 3), which answered its program from the drone's replies of 2 and 3. Its
    request 4 says so (``adopted_from_reqnr``): they count as brought in epoch 3, newer
    than 4's give-up, so a later taker holding it finds it replaced. A master not granted
    by takeover, another epoch, or nothing adopted changes nothing."""
    seq = Sequencer([0, 4, 1, 3], initial_master=0)
    for reqnr in (1, 2, 3):
        serve(seq, 0, 1, reqnr)
    assert seq.adopt(0, 1, 2, 4) == []  # not a takeover
    seq.switch(4, SCRIPT, now=3.0)  # epoch 2
    seq.switch(1, LOST, now=4.0, takeover=True, lost_at=3.0)  # epoch 3
    assert seq.adopt(1, 2, 2, 4) == [] and seq.adopt(1, 3, 0, 4) == []
    adopted = seq.adopt(1, 3, 2, 4)
    assert [(r.reqnr, r.epoch) for r in adopted] == [(2, 3), (3, 3)]
    assert [(r.reqnr, r.epoch) for r in seq.replies_for_master(0)] == [(1, 1), (2, 3), (3, 3)]
    assert seq.cache.reqnrs == [1, 2, 3]  # in place: eviction's order unchanged
    assert seq.adopt(1, 3, 2, 5) == []  # said again: nothing more


def test_a_give_up_sent_along_replaces_the_reply_the_program_never_saw() -> None:
    """The master's program gave up on request 1, which the drone served; the give-up
    comes with request 2. A taker must see what the program saw: the give-up."""
    seq = Sequencer([0, 1, 2], initial_master=0)
    serve(seq, 0, 1, 1)
    gave_up = CachedReply(
        1, GET, DIGEST, b"", StatusError(grpc.StatusCode.CANCELLED, "gave up", (GIVEN_UP,))
    )
    assert seq.admit(0, 1, 2, GET, DIGEST, clock=[gave_up]) is None
    assert seq.keep([gave_up]) == (replace(gave_up, epoch=1),)  # brought in epoch 1
    seq.served(0, 2, GET, DIGEST, b"reply 2", 2.0, now=2.0)
    kept = seq.cache.get(1)
    assert kept is not None and kept.error is not None
    assert kept.error.code is grpc.StatusCode.CANCELLED and kept.to_proto().given_up
    # Another request under the number served, or a reply rather than a give-up: refused.
    other = CachedReply(2, GET, request_digest(GET, b"x"), b"", gave_up.error)
    with pytest.raises(StatusError) as wrong:
        seq.admit(0, 1, 3, GET, DIGEST, clock=[other])
    assert wrong.value.code is grpc.StatusCode.INVALID_ARGUMENT
    reply = CachedReply(2, GET, DIGEST, b"r")
    with pytest.raises(StatusError):
        seq.admit(0, 1, 3, GET, DIGEST, clock=[reply])


def test_give_ups_of_earlier_requests_served_may_come_along_again() -> None:
    """The program gave up on requests 1 and 2, both served: the master does not know
    whether its answers reached the drone, so both come along with request 3 (found by
    the simulation: refused INVALID_ARGUMENT before, request 3 never executed)."""
    seq = Sequencer([0, 1, 2], initial_master=0)
    serve(seq, 0, 1, 1)
    serve(seq, 0, 1, 2)
    error = StatusError(grpc.StatusCode.CANCELLED, "gave up", (GIVEN_UP,))
    gave_up = [CachedReply(1, GET, DIGEST, b"", error), CachedReply(2, GET, DIGEST, b"", error)]
    assert seq.admit(0, 1, 3, GET, DIGEST, clock=gave_up) is None
    seq.keep(gave_up)
    seq.served(0, 3, GET, DIGEST, b"reply 3", 3.0, now=3.0)
    for reqnr in (1, 2):
        kept = seq.cache.get(reqnr)
        assert kept is not None and kept.to_proto().given_up
    new_answer = CachedReply(4, "/baton.v1.Clock/Now", DIGEST, b"now")
    assert seq.admit(0, 1, 5, GET, DIGEST, clock=[*gave_up, new_answer]) is None
    with pytest.raises(StatusError) as late:  # one sent again after a new one: refused
        seq.admit(0, 1, 5, GET, DIGEST, clock=[new_answer, gave_up[0]])
    assert late.value.code is grpc.StatusCode.INVALID_ARGUMENT


def test_a_master_never_seen_is_lost_after_the_start_up_grace() -> None:
    """Not seen since the drone started: lost only once ``unseen_from`` (the end of the
    start-up grace) is ``after_s`` past; None (no controller seen yet) never."""
    seq = Sequencer([0, 1, 2], initial_master=0)
    seen = {1: 20.0, 2: 20.0}
    assert seq.takeover_due(99.0, {1, 2}, seen, after_s=3.0) is None
    assert seq.takeover_due(12.5, {1, 2}, seen, after_s=3.0, unseen_from=10.0) is None
    due = seq.takeover_due(13.0, {1, 2}, seen, after_s=3.0, unseen_from=10.0)
    assert due is not None and (due.new_master, due.lost, due.lost_at) == (1, 0, 10.0)
    # Made master later than the grace's end: counted from the switch.
    seq.switch(2, RPC, 50.0)
    assert seq.takeover_due(52.0, {0, 1}, {0: 52.0, 1: 52.0}, 3.0, unseen_from=10.0) is None
    due = seq.takeover_due(53.0, {0, 1}, {0: 53.0, 1: 53.0}, 3.0, unseen_from=10.0)
    assert due is not None and (due.new_master, due.lost) == (0, 2)


def test_a_master_taken_over_and_given_the_role_back_must_rejoin_first() -> None:
    """Simulation seed 16 (--lose-master): 0 was cut off, 2 took over, the script handed
    back to 0 cooperatively. 0 never heard of the takeover and still holds its epoch-1
    log: the drone refuses its Connect saying so, whoever is master now."""
    seq = Sequencer([0, 2, 1], initial_master=0)
    seq.switch(2, LOST, now=1.0, takeover=True, lost_at=0.5)  # epoch 2
    serve(seq, 2, 2, 1)
    seq.switch(0, SCRIPT, now=2.0)  # epoch 3, back to 0
    assert 0 not in seq.pending  # the takeover notice is not needed to fence it
    with pytest.raises(StatusError) as fenced:
        seq.admit_connect(0, mastership_epoch=1)
    assert fenced.value.code is grpc.StatusCode.FAILED_PRECONDITION
    assert ("baton-takeover", "1") in fenced.value.metadata
    assert dict(fenced.value.metadata)["baton-master"] == "0"
    # Rejoined with nothing (or restarted with nothing): granted.
    seq.admit_connect(0, mastership_epoch=0)
    # A mastership after the takeover is not fenced by it.
    seq.admit_connect(0, mastership_epoch=3)


def test_a_cooperative_switch_back_does_not_fence() -> None:
    """Issue 9 / F2: the role went away and came back before the old master heard;
    nobody acted without its log, so it goes on in the new epoch."""
    seq = Sequencer([0, 1], initial_master=0)
    serve(seq, 0, 1, 1)
    seq.switch(1, RPC, now=1.0)
    seq.switch(0, RPC, now=2.0)
    seq.admit_connect(0, mastership_epoch=1)
    assert seq.taken_over_since(0, 1) is None


def test_a_takeover_notice_is_moot_for_a_controller_holding_no_log_of_it() -> None:
    seq = Sequencer([0, 1], initial_master=0)
    serve(seq, 0, 1, 1)
    seq.switch(1, LOST, now=1.0, takeover=True)
    assert seq.pending[0].takeover
    with pytest.raises(StatusError) as fenced:
        seq.admit_connect(0, mastership_epoch=1)  # still holds its log: refused, fenced
    assert ("baton-takeover", "1") in fenced.value.metadata
    # Restarted with nothing: the notice would only make it rejoin again.
    with pytest.raises(StatusError) as not_master:
        seq.admit_connect(0, mastership_epoch=0)
    assert ("baton-takeover", "1") not in not_master.value.metadata
    assert 0 not in seq.pending


def test_the_fence_survives_a_drone_restart() -> None:
    """The notices owed are not kept by the store; the handover records are."""
    seq = Sequencer([0, 1], initial_master=0)
    serve(seq, 0, 1, 1)
    seq.switch(1, LOST, now=1.0, takeover=True)
    restarted = Sequencer([0, 1], initial_master=0)
    restarted.resume(1, seq.handovers, (1, 1, 0, 0), [], [], [])
    assert not restarted.pending
    error = refused(restarted, 0, 1, 2)  # its Invoke of epoch 1
    assert ("baton-takeover", "1") in error.metadata
    with pytest.raises(StatusError) as fenced:
        restarted.admit_connect(0, mastership_epoch=1)
    assert ("baton-takeover", "1") in fenced.value.metadata


def test_a_refusal_says_the_epoch_of_the_newest_takeover() -> None:
    """--lose-master seed 58: master 3 is cut off as the drone hands over to 1; the
    notice is lost. 1 dies waiting for 3's log, and 2 takes 1's mastership over. 3's
    own mastership was never taken over (``taken_over_since``), but its log never left
    it and 2 framed those replies from the drone's: the refusals say when the newest
    takeover was, so that 3, still ACTIVE in epoch 1, rejoins instead of sending it."""
    seq = Sequencer([3, 2, 0, 1], initial_master=3)
    serve(seq, 3, 1, 1)
    assert "baton-takeover-epoch" not in dict(refused(seq, 2, 1, 2).metadata)
    seq.switch(1, SCRIPT, now=2.0)  # epoch 2: 3's notice is lost
    seq.pending.clear()  # written to a stream the partition broke: counted delivered
    seq.switch(2, LOST, now=3.0, takeover=True, lost_at=2.0)  # epoch 3
    serve(seq, 2, 3, 2)
    seq.switch(0, SCRIPT, now=4.0)  # epoch 4, cooperative
    invoke = dict(refused(seq, 3, 1, 2).metadata)
    assert invoke["baton-master"] == "0" and "baton-takeover" not in invoke
    assert invoke["baton-takeover-epoch"] == "3"
    with pytest.raises(StatusError) as connect:
        seq.admit_connect(3, mastership_epoch=1)
    assert dict(connect.value.metadata)["baton-takeover-epoch"] == "3"
    assert seq.takeover_epoch == 3


def test_calls_the_master_answered_sent_again_are_taken_once() -> None:
    """The master gave up on request 2, whose Invoke carried its Sleep 1: not knowing
    whether the drone got them, it sends both again with request 3. The drone holds
    them already: request 3 is admitted (it was refused INVALID_ARGUMENT: the program
    saw a failure for a TakePicture; --lose-master seed 56) and nothing is kept twice."""
    seq = Sequencer([0, 1, 2], initial_master=0)
    sleep = CachedReply(1, "/baton.v1.Clock/Sleep", b"s", b"")
    assert seq.admit(0, 1, 2, GET, DIGEST, clock=[sleep]) is None
    seq.keep([sleep])
    seq.served(0, 2, GET, DIGEST, b"r2", 2.0, now=2.0)
    gave_up = CachedReply(
        2, GET, DIGEST, b"", StatusError(grpc.StatusCode.CANCELLED, "gave up", (GIVEN_UP,))
    )
    assert seq.admit(0, 1, 3, GET, DIGEST, clock=[sleep, gave_up]) is None
    kept = seq.keep([sleep, gave_up])
    assert [k.reqnr for k in kept] == [2]  # the give-up replaces reply 2; Sleep 1 is held
    seq.served(0, 3, GET, DIGEST, b"r3", 3.0, now=3.0)
    assert seq.cache.reqnrs == [1, 2, 3]


def test_a_handover_from_an_initial_master_never_connected_is_a_takeover() -> None:
    """Simulation finding F1 (--allow F1, most of its seeds): a Handover decided before the
    initial master connected. It was never ACTIVE and ignored the notice; the new master,
    refused at its start, waited for ever for a handover message."""
    seq = Sequencer([0, 1, 2], initial_master=0)
    assert seq.handover_must_take_over(1)
    seq.admit_connect(0)
    assert not seq.handover_must_take_over(1)  # connected: it goes ACTIVE and hands over
    served = Sequencer([0, 1, 2], initial_master=0)
    serve(served, 0, 1, 1)  # it served a request (before a drone restart, say)
    assert not served.handover_must_take_over(1)


# -- prepared handovers (docs/design.md, "Prepared handover") -------------------------


def progress(
    target: int, lacks: int, behind_s: float = 0.0, acked: int = 1
) -> drone_pb2.PreparationProgress:
    return drone_pb2.PreparationProgress(
        target=target, lacks_bytes=lacks, behind_s=behind_s, acked=acked
    )


def serve_with(
    seq: Sequencer, reqnr: int, word: drone_pb2.PreparationProgress | None, reply: bytes
):  # type: ignore[no-untyped-def]
    assert seq.admit(0, 1, reqnr, GET, DIGEST) is None
    seq.note_progress(0, 1, word)
    return seq.served(0, reqnr, GET, DIGEST, reply, float(reqnr), now=float(reqnr))


def test_a_prepared_handover_moves_the_master_once_the_target_lacks_little() -> None:
    seq = Sequencer([0, 1, 2], initial_master=0, prepare_timeout_s=10.0)
    serve(seq, 0, 1, 1)
    notice = seq.prepare(2, RPC, now=1.0)
    assert (notice.target, notice.epoch, notice.timeout_s) == (2, 1, 10.0)
    # Not heard yet, then far behind: the master stays.
    assert serve_with(seq, 2, None, b"r").handover is None
    assert serve_with(seq, 3, progress(2, 1 << 20), b"r").handover is None
    # Little left, but this request's reply is a picture: not yet.
    assert serve_with(seq, 4, progress(2, 100), b"p" * (20 << 10)).handover is None
    # Little left and acknowledged lately, but a word about another target: ignored.
    assert serve_with(seq, 5, progress(1, 100), b"r").handover is None
    # Little left, but its oldest message waits for an acknowledgement: a frozen target.
    assert serve_with(seq, 6, progress(2, 100, behind_s=0.3), b"r").handover is None
    # Little left, nothing waits, but nothing acknowledged since the preparation began.
    assert serve_with(seq, 7, progress(2, 100, acked=0), b"r").handover is None
    record = serve_with(seq, 8, progress(2, 100, behind_s=0.05), b"r").handover
    assert record is not None and (record.kind, record.new_master, record.epoch) == (
        drone_pb2.HANDOVER_KIND_PREPARED,
        2,
        2,
    )
    assert (record.prepare_started_at, record.prepare_lacked_bytes) == (1.0, 101)
    assert not record.prepare_timed_out and seq.preparing is None
    assert seq.pending[0].new_master == 2  # the old master's notice, as for any switch


def test_a_prepared_handover_is_forced_at_its_timeout_with_or_without_a_request() -> None:
    seq = Sequencer([0, 1, 2], initial_master=0, prepare_timeout_s=2.0)
    serve(seq, 0, 1, 1)
    seq.prepare(1, SCRIPT, now=1.0)
    assert seq.preparation_expired(2.9) is None
    forced = seq.preparation_expired(3.0)
    assert forced is not None and (forced.kind, forced.prepare_timed_out) == (
        drone_pb2.HANDOVER_KIND_COOPERATIVE,
        True,
    )
    assert forced.trigger == SCRIPT and seq.master == 1
    # After a request: the same at its end, if the target is still behind.
    seq2 = Sequencer([0, 1], initial_master=0, prepare_timeout_s=2.0)
    seq2.prepare(1, RPC, now=0.0)
    assert serve_with(seq2, 1, progress(1, 1 << 20), b"r").handover is None
    late = serve_with(seq2, 2, progress(1, 1 << 20), b"r").handover
    assert (
        late is not None
        and late.prepare_timed_out
        and late.kind == drone_pb2.HANDOVER_KIND_COOPERATIVE
    )


def test_a_word_between_requests_moves_the_master_once_the_target_caught_up() -> None:
    seq = Sequencer([0, 1, 2], initial_master=0, prepare_timeout_s=10.0)
    serve(seq, 0, 1, 1)
    notice = seq.prepare(2, RPC, now=1.0)
    assert notice.bound_bytes == PREPARED_BOUND_BYTES  # the master reports within it

    def word(
        target: int = 2, lacks: int = 100, after: int = 1, behind_s: float = 0.0, acked: int = 1
    ) -> drone_pb2.HandoverRecord | None:
        w = progress(target, lacks, behind_s, acked)
        w.after_reqnr = after
        return seq.progress_between(0, 1, w, now=2.0)

    # Not the master, another epoch, another target, or still behind: nothing moves.
    assert seq.progress_between(1, 1, progress(2, 100), now=2.0) is None
    assert seq.progress_between(0, 2, progress(2, 100), now=2.0) is None
    assert word(target=1) is None
    assert word(lacks=PREPARED_BOUND_BYTES + 1) is None
    assert word(behind_s=0.3) is None and word(acked=0) is None
    # Before the deadline a word never forces: only a caught-up target moves the master.
    assert seq.progress_between(0, 1, progress(2, 1 << 20), now=100.0) is None
    assert seq.preparing is not None
    # A word written before request 2 was served misses its reply: ignored.
    serve_with(seq, 2, None, b"p" * (1 << 20))
    assert word(after=1) is None and seq.master == 0
    record = word(after=2)
    assert record is not None and (record.kind, record.new_master, record.after_reqnr) == (
        drone_pb2.HANDOVER_KIND_PREPARED,
        2,
        2,
    )
    assert (record.prepare_lacked_bytes, record.decided_at) == (100, 2.0)
    assert seq.preparing is None and seq.pending[0].new_master == 2


def test_any_switch_ends_a_preparation_and_the_master_itself_is_refused() -> None:
    seq = Sequencer([0, 1, 2], initial_master=0)
    with pytest.raises(StatusError) as itself:
        seq.prepare(0, RPC, now=0.0)
    assert itself.value.code is grpc.StatusCode.FAILED_PRECONDITION
    seq.prepare(2, RPC, now=0.0)
    seq.switch(1, LOST, now=1.0, takeover=True)
    assert seq.preparing is None and seq.preparation_expired(100.0) is None


def test_a_prepared_script_line_is_begun_again_after_a_restart_before_its_handover() -> None:
    """A drone restart loses the preparation (it is not in the store), and the line
    was stored as fired when it began: the scripted handover never happened. The line
    fires once the preparation ends, so the restarted drone begins it again."""
    script = {2: ScriptedHandover(2, 1, 1, prepared=True)}
    seq = Sequencer([0, 1], initial_master=0, script=script, prepare_timeout_s=5.0)
    serve(seq, 0, 1, 1)
    serve(seq, 0, 1, 2)
    assert seq.preparing is not None and seq.fired_script == []
    # The drone restarts: what the store kept.
    again = Sequencer([0, 1], initial_master=0, script=script, prepare_timeout_s=5.0)
    counts = (seq.last_reqnr, seq.executed, seq.duplicates, seq.rejected)
    again.resume(seq.master, seq.handovers, counts, [], seq.audit, seq.fired_script)
    assert again.preparing is None
    assert again.admit(0, 1, 3, GET, DIGEST) is None
    served = again.served(0, 3, GET, DIGEST, b"r", 3.0, now=3.0)
    assert served.prepare is not None and served.prepare.target == 1
    forced = again.preparation_expired(8.0)
    assert forced is not None and again.master == 1 and again.fired_script == [2]
    # A preparation an operator's replaced ends as fired too.
    seq = Sequencer([0, 1, 2], initial_master=0, script=dict(script))
    serve(seq, 0, 1, 1)
    serve(seq, 0, 1, 2)
    seq.prepare(2, RPC, now=2.5)
    assert seq.preparing is not None and seq.preparing.target == 2 and seq.fired_script == [2]


def test_a_script_line_due_while_an_earlier_lines_preparation_is_under_way_waits() -> None:
    """Lines 2 and 3 both prepared: at request 3 the target of line 2 has not caught up.
    Line 3 waits for line 2's handover and begins its own preparation after it; it does
    not replace line 2's, which dropped that handover (CI at 5e5646f)."""
    script = {2: ScriptedHandover(2, 1, 1, True), 3: ScriptedHandover(3, 2, 2, True)}
    seq = Sequencer([0, 1, 2], initial_master=0, script=script, prepare_timeout_s=5.0)
    for reqnr in (1, 2, 3):
        serve(seq, 0, 1, reqnr)
    assert seq.preparing is not None and seq.preparing.target == 1 and seq.fired_script == []
    forced = seq.preparation_expired(8.0)
    assert forced is not None and seq.master == 1 and seq.fired_script == [2]
    assert seq.admit(1, 2, 4, GET, DIGEST) is None
    served = seq.served(1, 4, GET, DIGEST, b"r", 9.0, now=9.0)
    assert served.prepare is not None and served.prepare.target == 2 and seq.master == 1
    assert seq.preparing is not None and seq.preparing.line == 3


def test_a_script_line_marked_prepared_begins_a_preparation() -> None:
    script = {2: ScriptedHandover(2, 1, 1, prepared=True)}
    seq = Sequencer([0, 1], initial_master=0, script=script)
    serve(seq, 0, 1, 1)
    assert seq.admit(0, 1, 2, GET, DIGEST) is None
    served = seq.served(0, 2, GET, DIGEST, b"r", 2.0, now=2.0)
    assert served.handover is None and served.prepare is not None
    assert served.prepare.target == 1 and seq.master == 0


def test_a_new_master_that_spoke_on_a_preparation_held_its_old_masters_log() -> None:
    """--lose-master --prepared seed 1439: after the mission's last request, 5 hands over
    to 2 and 2 (ACTIVE: it prepares a handover to 3 and says so between requests) to 3;
    5 is then lost. No new master sent a request, but 2's word proves 5's log arrived:
    no takeover. (One was decided; it fenced the ACTIVE master and lost its log.)"""
    seq = Sequencer([5, 2, 3], initial_master=5)
    serve(seq, 5, 1, 1)
    seq.switch(2, SCRIPT, now=1.0)  # epoch 2
    seq.prepare(3, RPC, now=1.1)
    word = drone_pb2.PreparationProgress(target=3, lacks_bytes=1 << 20, after_reqnr=1)
    assert seq.progress_between(2, 2, word, now=1.2) is None  # not caught up
    seq.switch(3, RPC, now=1.3)  # epoch 3
    seen = {5: 1.0, 2: 9.0, 3: 9.0}
    assert seq.takeover_due(9.0, {2, 3}, seen, after_s=3.0) is None
    # Without the word, 5's log may never have left it: 3 is granted again.
    silent = Sequencer([5, 2, 3], initial_master=5)
    serve(silent, 5, 1, 1)
    silent.switch(2, SCRIPT, now=1.0)
    silent.switch(3, RPC, now=1.3)
    due = silent.takeover_due(9.0, {2, 3}, seen, after_s=3.0)
    assert due is not None and (due.new_master, due.lost) == (3, 5)


def test_a_masters_fresh_self_that_gave_its_mastership_up_is_granted_a_new_epoch() -> None:
    """--policy nearest seed 48: master 4 (epoch 3 here) flushed a message on a framing it
    then gave up, and rejoined with nothing; its fresh self says so on Connect. Granted
    the same epoch, its messages could not be told apart from that one: it takes over
    from its earlier self in a new epoch, and owes itself no notice. A second Connect
    before the first Connected (it says the same) is granted that epoch as it is."""
    seq = Sequencer([4, 0, 3], initial_master=4)
    seq.switch(0, LOST, now=1.0, takeover=True)  # epoch 2
    seq.switch(4, LOST, now=2.0, takeover=True)  # epoch 3
    assert not seq.fresh_self_due(4, mastership_epoch=0, given_up_epoch=0)
    assert not seq.fresh_self_due(0, mastership_epoch=0, given_up_epoch=3)  # not master
    assert not seq.fresh_self_due(4, mastership_epoch=3, given_up_epoch=3)  # holds its log
    assert seq.fresh_self_due(4, mastership_epoch=0, given_up_epoch=3)
    record = seq.take_over_from_earlier_self(4, now=3.0)
    assert (record.old_master, record.new_master, record.epoch) == (4, 4, 4)
    assert record.kind == drone_pb2.HANDOVER_KIND_TAKEOVER and seq.granted_by_takeover
    assert 4 not in seq.pending
    assert not seq.fresh_self_due(4, mastership_epoch=0, given_up_epoch=3)  # the second
    seq.admit_connect(4, mastership_epoch=0)
    assert seq.connected_epoch == 4
    with pytest.raises(StatusError) as fenced:
        seq.admit_connect(4, mastership_epoch=3)  # the earlier self's log: given up
    assert ("baton-takeover", "1") in fenced.value.metadata


def seal(grant: drone_pb2.Grant) -> None:
    """A stand-in for the drone's key: what it signed, readable."""
    grant.signature = b"%d:%d:%d" % (grant.master, grant.epoch, grant.kind)


def test_every_grant_is_signed_and_said_with_the_event_that_makes_a_master() -> None:
    seq = Sequencer([0, 1, 2], initial_master=0)
    assert seq.signed_grant(1) is None  # an insecure drone says no grant
    assert "baton-grant" not in dict(refused(seq, 1, 0, 1).metadata)
    seq.sign_grants_with(seal)
    assert seq.grant_of(1) == drone_pb2.Grant(
        master=0, epoch=1, kind=drone_pb2.GRANT_KIND_FIRST, signature=b"0:1:1", old_master=0
    )
    seq.switch(1, RPC, now=1.0)
    # The old master's notice carries the new master's grant, for its handover message.
    notice = seq.pending[0]
    assert notice.grant == drone_pb2.Grant(
        master=1, epoch=2, kind=drone_pb2.GRANT_KIND_HANDOVER, signature=b"1:2:2", old_master=0
    )
    # A refusal names the master with its grant, so a refused old master hands over too.
    said = dict(refused(seq, 0, 1, 1).metadata)
    assert drone_pb2.Grant.FromString(bytes.fromhex(said["baton-grant"])) == notice.grant
    seq.switch(2, LOST, now=2.0, takeover=True)
    assert seq.grant_of(3).kind == drone_pb2.GRANT_KIND_TAKEOVER
    assert (seq.grant_of(3).master, seq.grant_of(3).old_master) == (2, 1)  # taken from 1
    # The first master's grant is still said right after it was replaced, and a drone
    # restarted from its store grants each epoch as before (its key is its certificate's).
    assert seq.grant_of(1).master == 0
    restarted = Sequencer([0, 1, 2], initial_master=0)
    restarted.sign_grants_with(seal)
    restarted.resume(seq.master, seq.handovers, (0, 0, 0, 0), [], [], [])
    assert [restarted.grant_of(e) for e in (1, 2, 3)] == [seq.grant_of(e) for e in (1, 2, 3)]


def test_a_framing_a_takeover_replaced_is_known_by_the_log_numbers_its_taker_framed() -> None:
    """--policy predictive 19072 and the 2810 kind: the taker of epoch 2 said its own
    messages follow message 12 (``framed_after_lognr``): from 13 on the ring's log is
    of epoch 2 or newer. A later taker whose top message is numbered 13 or more and
    older than epoch 2 holds another framing of those numbers; one below 13, or of
    epoch 2 or newer, does not. A later takeover that frames from a lower number
    takes over the numbers above it."""
    seq = Sequencer([0, 1, 2], initial_master=0)
    serve(seq, 0, 1, 1)
    seq.switch(1, LOST, now=4.0, takeover=True, lost_at=1.0)  # epoch 2
    assert seq.replaced_framing(15, 1) is None  # nobody said where its framing starts
    seq.note_framing(0, 2, (9, 1))  # not the master: nothing
    seq.note_framing(1, 1, (9, 1))  # not its epoch: nothing
    seq.note_framing(1, 2, (12, 1))
    seq.note_framing(1, 2, (14, 2))  # only the first counts
    assert seq.handovers[-1].framed_after_lognr == 12
    assert seq.replaced_framing(15, 1) == (13, 2)
    assert seq.replaced_framing(13, 1) == (13, 2)
    assert seq.replaced_framing(12, 1) is None
    assert seq.replaced_framing(15, 2) is None and seq.replaced_framing(15, 3) is None
    seq.switch(2, LOST, now=6.0, takeover=True, lost_at=5.0)  # epoch 3
    seq.note_framing(2, 3, (10, 1))
    assert seq.replaced_framing(11, 2) == (11, 3)  # epoch 2's 11 and 12 are replaced too
    assert seq.replaced_framing(10, 1) is None
    seq.switch(0, RPC, now=7.0)  # cooperative: frames nothing anew
    seq.note_framing(0, 4, (3, 1))
    assert seq.replaced_framing(11, 2) == (11, 3)


def test_a_takers_start_that_did_not_last_no_longer_counts() -> None:
    """--policy nearest 13594: taker 1 (epoch 2) framed from message 6, and its messages
    never left it (cut off, then fenced). Taker 3 (epoch 3) went ACTIVE on the lost
    master's messages 6-7 of epoch 1, which the ring still held, and built on them:
    those are the ring's, and a later taker holding them (7 of epoch 1) is not told
    they were replaced. Judged by epoch 2's start alone, it was refused, refused the
    ring's 6-7, and waited for them for ever."""
    seq = Sequencer([0, 1, 2, 3], initial_master=0)
    serve(seq, 0, 1, 1)
    seq.switch(1, LOST, now=4.0, takeover=True, lost_at=1.0)  # epoch 2
    seq.note_framing(1, 2, (5, 1))
    assert seq.replaced_framing(7, 1) == (6, 2)
    seq.switch(3, LOST, now=6.0, takeover=True, lost_at=5.0)  # epoch 3
    seq.note_framing(3, 3, (7, 1))
    assert seq.replaced_framing(7, 1) is None
    assert seq.replaced_framing(9, 1) == (8, 3)
