"""Algorithm 1's state machine, driven by messages in chosen orders (no sockets)."""

from __future__ import annotations

import pytest
from helpers.protocol import started

from baton.controller.protocol import (
    ConnectDrone,
    ControllerProtocol,
    DisconnectDrone,
    Diverged,
    NonDeterminismError,
    ProtocolError,
    Refusal,
    ReplacedFraming,
    SeenNumbers,
    SendLog,
    State,
    entry_size,
    request_digest,
    resend_after,
    ring_route,
)
from baton.rpc.errors import StatusError
from baton.v1 import drone_pb2, ring_pb2

GET = "/baton.v1.Mobility/GetPosition"
PICTURE = "/baton.v1.Camera/TakePicture"


def entry(
    reqnr: int, method: str = GET, reply: bytes = b"", request: bytes = b""
) -> ring_pb2.LogEntry:
    return ring_pb2.LogEntry(
        reqnr=reqnr,
        method=method,
        reply=reply or f"reply {reqnr}".encode(),
        request=request,
        request_digest=request_digest(method, request),
    )


def message(
    lognr: int, origin: int, reqnrs: range | list[int], handover: bool = False, sender: int = -1
) -> ring_pb2.LogMessage:
    return ring_pb2.LogMessage(
        lognr=lognr,
        origin=origin,
        handover=handover,
        entries=[entry(n) for n in reqnrs],
        sender=origin if sender < 0 else sender,
    )


def sends(effects: list) -> list[tuple[int, int, bool]]:
    return [
        (e.dest, e.message.lognr, e.message.handover) for e in effects if isinstance(e, SendLog)
    ]


def replay_all(p: ControllerProtocol) -> list:
    effects: list = []
    while p.state is State.REPLAY:
        _, more = p.replay(GET, b"")
        effects.extend(more)
    return effects


def test_every_controller_starts_passive_and_asks_the_drone() -> None:
    master = ControllerProtocol(0, [0, 1, 2], 0)
    other = ControllerProtocol(1, [0, 1, 2], 0)
    for p in (master, other):
        assert (p.state, p.master, p.start()) == (State.PASSIVE, False, [ConnectDrone()])
    assert (other.predecessor, other.successor) == (0, 2)
    # The drone's grant makes the initial master ACTIVE once its predecessor has
    # said what it holds (nothing, at the start), in either order.
    assert master.on_granted(1) == []
    assert master.state is State.PASSIVE and master.master
    assert master.on_sync(0) == [ConnectDrone()]
    assert (master.state, master.epoch) == (State.ACTIVE, 1)
    assert other.on_sync(0) == [] and other.state is State.PASSIVE


def test_a_controller_granted_the_role_after_a_restart_catches_up_first() -> None:
    """Issue 9, defect 3: never ACTIVE on its own word, never over log numbers in use."""
    p = ControllerProtocol(1, [0, 1, 2], 0)
    p.start()
    assert p.on_granted(4) == []  # the drone says: master, epoch 4
    assert p.on_sync(3) == []  # the predecessor holds 1..3 and re-sends them
    # Messages it once created itself come back in the history: handled, not
    # forwarded again (they have been round).
    assert sends(p.on_log(message(1, 0, [1]))) == [(2, 1, False)]
    ours = message(2, 1, [2])
    ours.epoch = 4  # logged in its mastership (a cooperative grant waits for one, F4)
    assert sends(p.on_log(ours)) == []
    replay_all(p)
    assert p.state is State.PASSIVE and not p.caught_up
    p.on_log(message(3, 1, [3]))
    effects = replay_all(p)
    assert effects == [ConnectDrone()] and p.state is State.ACTIVE
    assert (p.reqnr, p.lognr, p.epoch) == (3, 3, 4)


def test_a_refusal_is_judged_by_the_epoch_it_was_sent_in() -> None:
    """Issue 9, defect 4: a stale request's refusal never ends the mission."""
    p = started(0, [0, 1], 0)  # ACTIVE in epoch 1
    assert p.judge_refusal(1, master=1, epoch=2) is Refusal.HANDED_OVER
    assert p.judge_refusal(1, master=0, epoch=1) is Refusal.DISAGREE
    p.on_granted(3)  # the role came back: epoch 3
    assert p.judge_refusal(1, master=0, epoch=3) is Refusal.STALE
    assert p.judge_refusal(1, master=1, epoch=4) is Refusal.STALE
    assert p.judge_refusal(3, master=1, epoch=4) is Refusal.HANDED_OVER
    # Away to 1 and back in epoch 5 before the notice came (the drone dropped it).
    assert p.judge_refusal(3, master=0, epoch=5) is Refusal.REGRANTED
    p.on_handover_notice(1)
    assert p.judge_refusal(3, master=1, epoch=4) is Refusal.STALE  # not ACTIVE: nothing to do


def test_a_takeover_after_our_epoch_gives_up_the_log_we_still_hold() -> None:
    """--lose-master seed 58: ACTIVE in epoch 1 and never told of the handover to 1 in
    epoch 2, we are refused naming 2, which took 1's mastership over in epoch 3. Our log
    never left us and 2 framed those replies from the drone's: it is not sent (no
    handover message of ours in epoch 3), we rejoin with nothing."""
    p = started(3, [3, 2, 0, 1], 2**20, initial_master=3)
    p.on_reply(entry(1))
    assert not p.log_given_up(0)  # no takeover yet: the log goes to the new master
    assert not p.log_given_up(1)
    assert p.log_given_up(3)
    p.on_granted(4)  # the role came back cooperatively in epoch 4
    assert not p.log_given_up(3) and p.log_given_up(5)
    p.on_handover_notice(2, epoch=5)  # handed over: nothing of ours is held back
    assert not p.log_given_up(6)


def test_a_ring_message_of_a_newer_mastership_shows_an_active_master_it_was_taken_over() -> None:
    """--policy nearest: master 0, out of radio range, is taken over by 1 in epoch 2; the
    drone cannot tell it, the ring can: 1's message of epoch 2 shows the mastership went
    on without 0's log. Its own messages, older epochs, and a controller that is not
    ACTIVE (it handed over: nothing of its log is held back) show nothing."""
    p = started(0, [0, 1, 2], 2**20)
    p.on_reply(entry(1))
    taker = message(1, origin=1, reqnrs=[1])
    taker.epoch = 2
    assert p.went_on_without_us(taker)
    ours = message(1, origin=0, reqnrs=[1])
    ours.epoch = 2
    assert not p.went_on_without_us(ours)
    same = message(1, origin=1, reqnrs=[1])
    same.epoch = 1
    assert not p.went_on_without_us(same)
    p.on_handover_notice(1, epoch=2)
    assert not p.went_on_without_us(taker)


def test_a_fenced_master_handles_nothing_it_queued_before_its_rejoin() -> None:
    """--lose-master --prepared seed 242: master 3, cut off in epoch 1 with reply 1
    unflushed, queues the taker's message 1 (epoch 2, from request 1) and is fenced on
    it. Until the runtime rejoins with a fresh state, a sync frame must not drain that
    message into the given-up one (it expected request 2: a ProtocolError that stopped
    the mission)."""
    p = started(3, [3, 2, 1, 0], 2**20, initial_master=3)
    p.on_reply(entry(1))
    taker = message(1, origin=2, reqnrs=[1])
    taker.epoch = 2
    p.on_log(taker)
    assert p.went_on_without_us(taker)
    p.on_fenced(2)
    p.on_sync(1, 2)  # raised the ProtocolError before
    assert p.lognr == 0 and 1 in p.log_queue


def test_flush_limit_zero_flushes_after_every_reply() -> None:
    p = started(0, [0, 1], 0)
    for n in (1, 2, 3):
        assert sends(p.on_reply(entry(n))) == [(1, n, False)]
    assert (p.reqnr, p.lognr, len(p.log)) == (3, 3, 0)


def test_flush_limit_in_bytes_lets_the_log_exceed_it_by_one_entry() -> None:
    p = started(0, [0, 1], flush_limit=1000)
    assert p.on_reply(entry(1, reply=b"x" * 400)) == []
    assert p.on_reply(entry(2, reply=b"x" * 400)) == []
    effects = p.on_reply(entry(3, reply=b"x" * 5000))  # the paper's "e", a picture
    (flush,) = [e for e in effects if isinstance(e, SendLog)]
    assert [x.reqnr for x in flush.message.entries] == [1, 2, 3]
    assert flush.message.ByteSize() > 1000 + 5000
    assert p.log.size == 0


def test_reply_for_the_wrong_request_number_is_a_protocol_error() -> None:
    p = started(0, [0, 1], 0)
    with pytest.raises(ProtocolError, match="expected 1"):
        p.on_reply(entry(2))


def test_handover_notice_sends_unflushed_log_to_new_master_with_its_id_as_origin() -> None:
    p = started(0, [0, 1, 2, 3], flush_limit=10**6)
    p.on_reply(entry(1))
    p.on_reply(entry(2))
    effects = p.on_handover_notice(2)
    assert effects[0] == DisconnectDrone()
    (send,) = [e for e in effects if isinstance(e, SendLog)]
    assert (send.dest, send.message.lognr, send.message.origin, send.message.handover) == (
        2,
        1,
        2,
        True,
    )
    assert [x.reqnr for x in send.message.entries] == [1, 2]
    assert (p.state, p.master, p.lognr) == (State.PASSIVE, False, 1)
    assert p.on_handover_notice(2) == []  # a repeated notice changes nothing


def test_a_handover_notice_older_than_our_takeover_is_ignored() -> None:
    """Across real processes (test_restarts_and_epochs): master 1 (epoch 2) was moved to
    a just-restarted 0 (epoch 3), which the drone, not having seen 0 since its kill,
    took over at once, giving 1 the mastership again (epoch 4). The epoch-3 notice
    reached 1 after that takeover: 1 handed over to 0, which the takeover had fenced,
    and nobody was master, for ever. A notice of an epoch not above ours is stale."""
    p = started(1, [0, 1, 2], 0, initial_master=1)
    p.on_reply(entry(1))
    p.on_granted(4, takeover=True)
    assert p.on_handover_notice(0, epoch=3) == []
    assert (p.state, p.master, p.epoch) == (State.ACTIVE, True, 4)
    # The notice of a switch after our own epoch still hands over.
    assert sends(p.on_handover_notice(0, epoch=5))[-1][2] is True
    assert p.state is State.PASSIVE


def test_passive_controller_replays_an_in_order_message_and_forwards_it() -> None:
    p = started(1, [0, 1, 2], 0)
    effects = p.on_log(message(1, origin=0, reqnrs=[1, 2]))
    assert sends(effects) == [(2, 1, False)]
    assert p.state is State.REPLAY
    reply, _ = p.replay(GET, b"")
    assert reply.reqnr == 1 and p.reqnr == 1
    _, effects = p.replay(GET, b"")
    assert p.state is State.PASSIVE and p.reqnr == 2 and effects == []


def test_message_is_not_forwarded_to_its_origin() -> None:
    p = started(2, [0, 1, 2], 0)
    assert sends(p.on_log(message(1, origin=0, reqnrs=[1]))) == []


def test_in_order_message_during_replay_is_queued_not_dropped() -> None:
    """docs/design.md note 1: line 44 would drop lognr = lognr + 1 arriving in REPLAY."""
    p = started(1, [0, 1, 2], 0)
    p.on_log(message(1, origin=0, reqnrs=[1]))
    p.on_log(message(2, origin=0, reqnrs=[2]))  # arrives while replaying 1
    p.on_log(message(3, origin=0, reqnrs=[3]))
    assert p.state is State.REPLAY and sorted(p.log_queue) == [2, 3]
    replies = [p.replay(GET, b"")[0].reqnr for _ in range(3)]
    assert replies == [1, 2, 3]
    assert (p.state, p.lognr, p.log_queue) == (State.PASSIVE, 3, {})


def test_handover_message_overtaking_earlier_flushes_waits_for_them() -> None:
    new = started(2, [0, 1, 2, 3], 0)
    # Flushes 1 and 2 travel around the ring (0 -> 1 -> 2); the handover
    # message 3 goes straight from 0 to 2 and arrives first.
    effects = new.on_log(message(3, origin=2, reqnrs=[3], handover=True, sender=0))
    assert sends(effects) == [(3, 3, False)]  # forwarded at once, as a normal message
    assert new.state is State.PASSIVE and not new.master and list(new.log_queue) == [3]
    new.on_log(message(2, origin=0, reqnrs=[2]))
    assert new.state is State.PASSIVE  # still missing 1
    new.on_log(message(1, origin=0, reqnrs=[1]))
    assert new.state is State.REPLAY
    effects = replay_all(new)
    assert new.master and new.state is State.ACTIVE and ConnectDrone() in effects
    assert (new.reqnr, new.lognr) == (3, 3)


def test_new_master_with_empty_handover_log_goes_active_at_once() -> None:
    new = started(1, [0, 1], 0)
    effects = new.on_log(message(1, origin=1, reqnrs=[], handover=True, sender=0))
    assert new.state is State.ACTIVE and new.master
    assert ConnectDrone() in effects and sends(effects) == [(0, 1, False)]


def test_old_master_forwards_its_own_handover_message_back_but_ignores_it() -> None:
    """Footnote 3: the old master gets the message back and skips it by lognr."""
    old = started(0, [0, 1, 2, 3], 0)
    old.on_reply(entry(1))
    old.on_handover_notice(2)  # lognr 2: the handover message, origin 2
    back = message(2, origin=2, reqnrs=[], sender=3)
    effects = old.on_log(back)
    assert sends(effects) == [(1, 2, False)]  # controller 1 still needs it
    assert old.state is State.PASSIVE and old.log_queue == {} and old.lognr == 2


def test_replicated_message_resent_after_reconnect_is_ignored_whole() -> None:
    p = started(1, [0, 1, 2], 0)
    p.on_log(message(1, origin=0, reqnrs=[1]))
    assert p.on_log(message(1, origin=0, reqnrs=[1])) == []


def test_empty_non_handover_message_lets_the_queue_drain() -> None:
    """The pseudo-code stays PASSIVE after an empty in-order message and never looks at logQ."""
    p = started(3, [0, 1, 2, 3], 0)
    p.on_log(message(2, origin=1, reqnrs=[1]))  # the new master's first flush, early
    p.on_log(message(1, origin=1, reqnrs=[], sender=1))  # the (empty) handover message, forwarded
    assert p.state is State.REPLAY and p.lognr == 2


def test_handover_during_an_in_flight_call_leaves_the_reply_to_the_new_master() -> None:
    """Footnote 2: the notice overtakes the reply of request 3."""
    old = started(0, [0, 1], flush_limit=10**6)
    new = started(1, [0, 1], flush_limit=10**6)
    old.on_reply(entry(1))
    old.on_reply(entry(2))
    # Request 3 is in flight; the drone served it and then sent the notice.
    (send,) = [e for e in old.on_handover_notice(1) if isinstance(e, SendLog)]
    with pytest.raises(ProtocolError):
        old.on_reply(entry(3))  # the runtime discards it instead
    new.on_log(send.message)
    replay_all(new)
    assert new.state is State.ACTIVE and new.reqnr == 2  # re-sends 3; the drone's cache answers
    flush = new.on_reply(entry(3))
    assert flush == []  # below the limit: stays in the new master's log
    assert [x.reqnr for x in new.log.entries] == [3]


def test_determinism_guard_shows_both_requests() -> None:
    p = started(1, [0, 1], 0)
    p.on_log(message(1, origin=0, reqnrs=[1]))
    with pytest.raises(NonDeterminismError) as caught:
        p.replay(PICTURE, b"\x08\x01")
    text = str(caught.value)
    # Both requests decoded as `baton replay` shows them.
    assert "request 1" in text and "Mobility.GetPosition {}" in text
    assert "Camera.TakePicture {" in text and "request bytes" not in text
    assert p.state is State.REPLAY and p.reqnr == 0  # nothing consumed


def test_message_skipping_a_request_number_is_a_protocol_error() -> None:
    p = started(1, [0, 1], 0)
    with pytest.raises(ProtocolError, match="starts at request 5"):
        p.on_log(message(1, origin=0, reqnrs=[5]))


def test_a_replica_that_cannot_handle_a_message_still_forwards_it() -> None:
    """Issue 9, defect 9: the replicas after a failed one must not be starved."""
    p = started(1, [0, 1, 2], 0)
    with pytest.raises(ProtocolError) as caught:
        p.on_log(message(1, origin=0, reqnrs=[5]))
    assert sends(caught.value.effects) == [(2, 1, False)]


def test_mission_done_flushes_the_masters_last_entries() -> None:
    p = started(0, [0, 1], flush_limit=10**6)
    p.on_reply(entry(1))
    assert sends(p.on_mission_done()) == [(1, 1, False)]
    assert p.on_mission_done() == []


def test_an_entry_logged_after_the_mission_ended_is_flushed_at_once() -> None:
    """--prepared seed 3527 (the simulation): master 0 handed over to 1, its program
    gave up on its last call (request 2) while PASSIVE and ended; 1 handed back, and 0,
    ACTIVE again, settled the call by logging the give-up (node.py
    ``_settle_after_the_end``), below the flush limit. No end of the mission came to
    flush it: replica 1 waited for request 2 for ever."""
    p = started(0, [0, 1], flush_limit=10**6)
    p.on_reply(entry(1))
    assert sends(p.on_handover_notice(1, epoch=2)) == [(1, 1, True)]
    assert p.on_mission_done() == []  # PASSIVE: nothing to flush
    back = message(2, origin=0, reqnrs=[], handover=True, sender=1)
    back.epoch, back.after_reqnr, back.after_epoch = 3, 1, 2
    p.on_log(back)
    p.on_granted(3)
    assert p.state is State.ACTIVE
    assert sends(p.on_reply(entry(2))) == [(1, 3, False)]


def test_seen_log_numbers_stay_a_watermark_when_they_arrive_in_order() -> None:
    """Issue 9, defect 8: the set of received log numbers grew by one per message."""
    seen = SeenNumbers()
    for number in range(1, 10_001):
        seen.add(number)
    assert len(seen) == 0 and seen.upto == 10_000 and 10_000 in seen and 10_001 not in seen
    seen.add(10_003)  # a gap: kept above the watermark until it closes
    assert 10_003 in seen and 10_002 not in seen and len(seen) == 1
    seen.add(10_002)
    seen.add(10_001)
    assert len(seen) == 0 and seen.upto == 10_003


def test_a_handover_message_carries_the_new_masters_epoch() -> None:
    """A Connect refusal the drone made before it granted that epoch is stale."""
    old, new = started(0, [0, 1], 0), started(1, [0, 1], 0)
    (send,) = [e for e in old.on_handover_notice(1, epoch=2) if isinstance(e, SendLog)]
    assert send.message.epoch == 2 and send.message.handover
    new.on_log(send.message)
    assert (new.master, new.epoch) == (True, 2)
    assert new.connect_refusal_is_stale(1) and not new.connect_refusal_is_stale(2)


def test_the_received_watermark_moves_over_a_masters_own_flushes() -> None:
    """Issue 9, defect 8: it stalled at the first own flush and grew for the rest."""
    master = started(0, [0, 1], 0)
    for reqnr in range(1, 6):
        master.on_reply(entry(reqnr))
    master.on_handover_notice(1)  # lognr 6: the handover message, comes back later
    # Not held until it comes back (F10): a predecessor re-sending from the hello gives it.
    assert master.holds_lognr == 5 and len(master._received) == 0
    master.on_log(message(6, 1, [], sender=1))  # its handover message, back as a normal one
    for lognr in range(7, 50):
        master.on_log(message(lognr, 1, []))
    assert master.holds_lognr == 49 and len(master._received) == 0


def test_the_watermark_is_what_the_masters_predecessor_holds_as_a_request_number() -> None:
    """Issue 10: the master gives the drone the highest request every controller holds."""
    master = started(0, [0, 1, 2], 0)
    for reqnr in (1, 2, 3):
        master.on_reply(entry(reqnr))  # flushes log messages 1, 2, 3
    assert master.watermark_reqnr == 0
    master.on_sync(2)  # controller 2 (and so 1) holds log messages 1..2
    assert master.watermark_reqnr == 2
    master.on_sync(3)
    assert master.watermark_reqnr == 3
    alone = started(0, [0], 0)
    alone.on_reply(entry(1))
    assert alone.watermark_reqnr == 1  # nobody else to hold it


def test_a_takeover_grant_goes_active_on_what_the_taker_holds() -> None:
    """The taker's predecessor may be the lost master: it never says what it holds."""
    taker = ControllerProtocol(1, [0, 1, 2], 0)
    taker.start()
    taker.on_log(message(1, 0, [1, 2]))
    assert taker.catch_up_to is None and taker.state is State.REPLAY
    assert taker.on_granted(2, takeover=True) == []
    assert replay_all(taker) == [ConnectDrone()]
    assert (taker.state, taker.master, taker.reqnr, taker.epoch) == (State.ACTIVE, True, 2, 2)


def test_a_taker_holding_less_than_the_drones_watermark_waits_for_the_ring() -> None:
    """A taker restarted with nothing: the drone let go of the replies every controller
    held (up to its watermark, 2), so the taker goes ACTIVE only once the ring gave it
    those; answering them itself would read another time, or re-send a request the
    drone can no longer answer."""
    taker = ControllerProtocol(1, [0, 1, 2], 0)
    taker.start()
    assert taker.on_granted(2, takeover=True, watermark_reqnr=2) == []
    assert taker.state is State.PASSIVE and not taker.caught_up
    taker.on_log(message(1, 0, [1, 2]))
    assert replay_all(taker) == [ConnectDrone()]
    assert (taker.state, taker.reqnr) == (State.ACTIVE, 2)


def test_a_fenced_masters_message_numbered_like_one_held_is_dropped_not_kept() -> None:
    """The taker's message 2 (epoch 2) is held; the fenced master, cut off, flushed its
    own 2 in epoch 1 (a give-up). That one is not the ring's: Fenced, not forwarded (a
    history that kept it would give it to a replica catching up: --lose-master seed 757)."""
    replica = ControllerProtocol(2, [0, 1, 2], 0)
    replica.start()
    ours = message(1, 1, [1])
    ours.epoch = 2
    replica.on_log(ours)
    replay_all(replica)
    stale = message(1, 0, [1])
    stale.epoch = 1
    effects = replica.on_log(stale)
    assert [type(e).__name__ for e in effects] == ["Fenced"] and not sends(effects)


def test_a_fenced_masters_late_messages_are_dropped_by_the_taker() -> None:
    taker = ControllerProtocol(1, [0, 1, 2], 0)
    taker.start()
    taker.on_log(message(1, 0, [1]))
    taker.on_granted(2, takeover=True)
    replay_all(taker)
    assert taker.state is State.ACTIVE
    stale = message(2, 0, [2])
    stale.epoch = 1  # logged by the lost master in its epoch
    effects = taker.on_log(stale)
    assert [type(e).__name__ for e in effects] == ["Fenced"] and not sends(effects)
    assert taker.on_reply(entry(2)) and taker.lognr == 2  # its own message 2 is the ring's


def test_a_fenced_master_sends_nothing_and_keeps_the_new_masters_messages() -> None:
    old = started(0, [0, 1, 2, 3], 2**20)
    old.on_reply(entry(1))
    assert len(old.log) == 1
    newer = message(1, 2, [1, 2])
    newer.epoch = 2  # a newer master's: we are the fenced one and do not know yet
    assert sends(old.on_log(newer)) == [(1, 1, False)]  # forwarded, not dropped
    assert 1 in old.log_queue
    assert old.on_fenced() == [DisconnectDrone()]
    assert (old.state, old.master, len(old.log)) == (State.PASSIVE, False, 0)


def test_a_message_numbered_like_ours_from_a_newer_epoch_means_we_must_rejoin() -> None:
    """A takeover's framing of the same replies: ours (never left a dead master) is not
    the ring's, and nothing past that number can be trusted."""
    old = started(0, [0, 1, 2], 2**20)
    old.on_reply(entry(1))
    old.on_handover_notice(1, epoch=2)  # handover message 1, lost with controller 1
    taker = message(1, 2, [1, 2, 3])
    taker.epoch = 3  # controller 2's, by takeover
    assert [type(e).__name__ for e in old.on_log(taker)] == ["Diverged"]
    again = message(1, 1, [1])
    again.epoch = 2  # our own handover message coming back: not a divergence
    assert old.on_log(again) == []


def test_the_ring_routes_to_the_first_successor_not_down_for_the_detection_time() -> None:
    down = {1: 5.0, 2: 0.4}  # seconds down; 3 has no stream tried yet
    ring = [0, 1, 2, 3]
    assert ring_route(ring, 0, down.get, 1.0) == (2, [1])
    assert ring_route(ring, 0, lambda pid: 9.0, 1.0) == (1, [])  # all down: the natural one
    assert ring_route(ring, 0, {1: 5.0, 2: 5.0}.get, 1.0) == (3, [1, 2])  # 3 is to be tried
    assert ring_route(ring, 3, down.get, 1.0) == (0, [])


def test_the_ring_stays_with_its_current_successor_when_every_one_is_down() -> None:
    """--lose-master seeds 4097, 5631, 10175: 1 routed around its dead successor 0 to 2,
    whose stream takes longer than the detection time to come up (a slow direction).
    Every one counted as down, the route went back to the dead 0, dropped the stream to
    2 and, tried again, never gave it the time to come up: the taker was never given the
    log. With every one down, the ring stays with the one it sends to."""
    ring = [1, 0, 2, 3]
    down = {0: 5.0, 2: 1.2, 3: 1.5}
    assert ring_route(ring, 1, down.get, 1.0, current=2) == (2, [0])
    assert ring_route(ring, 1, down.get, 1.0, current=3) == (3, [0, 2])
    assert ring_route(ring, 1, down.get, 1.0) == (0, [])  # none chosen yet: the natural one
    assert ring_route(ring, 1, {0: 5.0, 2: 1.2, 3: 0.5}.get, 1.0, current=2) == (3, [0, 2])


def test_a_master_cut_off_from_the_drone_does_not_route_around_its_successor() -> None:
    """--lose-master seed 956: one partition cut master 6 off from the drone and from its
    successor 1. 6 routed around 1 and its flushes (give-ups of requests that never
    reached the drone) went to the replicas after 1; the drone made 1 master by
    takeover, without them, and a later taker that held them built on a framing the
    drone had replaced. Cut off, the master waits; connected, it routes as before."""
    master = started(6, [5, 0, 2, 4, 6, 1, 3], 0, initial_master=6)
    assert not master.may_route_around([1], [], drone_connected=False)
    assert not master.may_route_around([1, 3], [1], drone_connected=False)  # one more
    assert master.may_route_around([1], [1, 3], drone_connected=False)  # back towards 1
    assert master.may_route_around([], [1], drone_connected=False)  # back to 1
    assert master.may_route_around([1], [], drone_connected=True)
    replica = started(3, [5, 0, 2, 4, 6, 1, 3], 0, initial_master=6)
    assert replica.may_route_around([5], [], drone_connected=False)  # it creates nothing


def test_a_next_message_of_a_newer_epoch_that_does_not_continue_ours_means_we_must_rejoin() -> None:
    replica = started(1, [0, 1, 2], 0)
    ours = message(1, 0, [1])
    ours.epoch = 2  # a master's flush that never left it: the drone took over
    replica.on_log(ours)
    replay_all(replica)
    ring = message(2, 0, [1, 2])  # the taker's message 2, framing request 1 again
    ring.epoch = 3
    assert [type(e).__name__ for e in replica.on_log(ring)] == ["SendLog", "Diverged"]
    other = started(1, [0, 1, 2], 0)
    other.on_log(ours)
    replay_all(other)
    stale = message(2, 0, [3])
    stale.epoch = 2  # not of a newer epoch: still the loud error
    with pytest.raises(ProtocolError):
        other.on_log(stale)


def test_a_handover_message_that_continues_another_framing_means_we_must_rejoin() -> None:
    """--lose-master seed 1943: the new master holds request 7 from a framing a takeover
    replaced; the handover message, without entries, says it follows request 6."""
    new_master = started(4, [0, 4, 5], 0)
    old = message(1, 0, [1, 2, 3, 4, 5, 6, 7])
    old.epoch = 6
    new_master.on_log(old)
    replay_all(new_master)
    handover = message(2, 4, [], handover=True, sender=0)
    handover.epoch, handover.after_reqnr = 9, 6
    assert [type(e).__name__ for e in new_master.on_log(handover)] == ["SendLog", "Diverged"]
    assert not new_master.master  # it does not go ACTIVE on a count that is not the ring's
    assert [m.lognr for m in new_master.kept_for_rejoin()] == [2]
    agreeing = started(4, [0, 4, 5], 0)
    agreeing.on_log(old)
    replay_all(agreeing)
    handover.after_reqnr = 7
    assert "TookOver" in [type(e).__name__ for e in agreeing.on_log(handover)]
    assert agreeing.master


def test_a_handover_message_that_follows_a_newer_framing_of_our_last_number() -> None:
    """--lose-master seed 1705: master 1, cut off from the drone, gave up on request 2
    (which the drone had executed) and flushed the give-up as message 2 of epoch 1; 5
    took over, framed request 2's reply as its message 2 of epoch 3 and handed over to
    6. The handover message overtook the ring's message 2 and follows request 2, as
    ours does: only the epoch of its creator's message 2 tells the framings apart."""
    p = ControllerProtocol(5, [1, 6, 5], 0)
    p.on_sync(0)
    p.on_granted(3, takeover=True)  # the taker, holding nothing
    p.on_reply(entry(1))
    p.on_reply(entry(2))
    (handover,) = [e.message for e in p.on_handover_notice(6, epoch=4) if isinstance(e, SendLog)]
    assert (handover.lognr, handover.after_reqnr, handover.after_epoch) == (3, 2, 3)
    replica = started(6, [1, 6, 5], 0, initial_master=1)
    first = message(1, 1, [1])
    first.epoch = 1
    replica.on_log(first)
    replay_all(replica)
    given_up = message(2, 1, [2])
    given_up.epoch = 1  # the fenced master's framing of request 2
    replica.on_log(given_up)
    replay_all(replica)
    handover.origin = 6
    assert [type(e).__name__ for e in replica.on_log(handover)] == ["SendLog", "Diverged"]
    assert not replica.master  # it does not go ACTIVE on a framing that is not the ring's
    assert [m.lognr for m in replica.kept_for_rejoin()] == [3]
    handover.after_epoch = 1  # built on our framing: taken
    agreeing = started(6, [1, 6, 5], 0, initial_master=1)
    for m in (first, given_up):
        agreeing.on_log(m)
        replay_all(agreeing)
    assert "TookOver" in [type(e).__name__ for e in agreeing.on_log(handover)]


def test_a_message_numbered_after_a_newer_mastership_by_an_older_one_is_dropped() -> None:
    """--lose-master seed 222: a master the drone replaced, cut off, handled the newer
    masters' messages and numbered its next one after them, in its old epoch."""
    replica = started(1, [0, 1, 2], 0)
    newer = message(1, 2, [1])
    newer.epoch = 3
    replica.on_log(newer)
    replay_all(replica)
    stale = message(2, 0, [2])
    stale.epoch = 1
    effects = replica.on_log(stale)
    assert [type(e).__name__ for e in effects] == ["Fenced"]  # not forwarded, not held
    assert 2 not in replica.log_queue and replica.lognr == 1
    ring = message(2, 0, [2])
    ring.epoch = 3
    assert sends(replica.on_log(ring)) == [(2, 2, False)]
    assert replica.lognr == 2


def _of_epoch(m: ring_pb2.LogMessage, epoch: int) -> ring_pb2.LogMessage:
    m.epoch = epoch
    m.after_reqnr = m.entries[0].reqnr - 1 if m.entries else 0
    return m


def test_a_new_master_does_not_wait_for_a_predecessor_that_holds_a_replaced_framing() -> None:
    """--lose-master seed 1402: a taker that held nothing renumbered the log and handed
    over to 0 (handover message 1, epoch 4); 0's predecessors still hold messages 1-2
    of the lost master's epoch 1, which a takeover replaced, and say so in their sync
    frames. Waiting for log message 2, 0 never went ACTIVE, and nothing of the ring's
    ever reached the predecessors to make them rejoin: every controller stalled."""
    ring = [2, 3, 1, 4, 0, 5]
    handover = _of_epoch(message(1, 0, [], handover=True, sender=3), 4)
    # The replaced framing's word after the new master handled its handover message.
    first = ControllerProtocol(0, ring, 0)
    first.start()
    assert first.on_granted(4) == []  # owed its handover message, and no word yet
    assert "TookOver" in [type(e).__name__ for e in first.on_log(handover)]
    assert first.state is State.PASSIVE
    assert first.on_sync(2, 1) == [ConnectDrone()]  # epoch 1 < 4: not the ring's log
    assert first.state is State.ACTIVE and first.lognr == 1
    # The same word before it: taken back once the handover message is handled.
    second = ControllerProtocol(0, ring, 0)
    second.start()
    second.on_granted(4)
    second.on_sync(2, 1)
    assert second.catch_up_to == 2
    assert ConnectDrone() in second.on_log(handover)
    assert second.state is State.ACTIVE and second.catch_up_to == 1
    # A word of the same framing (or one that does not say its epoch) is waited for.
    waiting = ControllerProtocol(0, ring, 0)
    waiting.start()
    waiting.on_granted(4)
    waiting.on_log(handover)
    waiting.on_sync(2, 4)
    waiting.on_sync(3, 0)
    assert waiting.state is State.PASSIVE and waiting.catch_up_to == 3
    assert waiting.missing_lognr == 2


def test_a_queued_message_of_a_replaced_framing_is_dropped_when_the_rings_comes() -> None:
    """--lose-master seed 1219: a controller that rejoined with nothing was given log
    message 3 of epoch 4 (the lost master's framing, from a predecessor that had not
    seen the ring's yet) before the ring's message 1 of epoch 6 (a taker's, which
    renumbered the log). Queued, 3 stood for a gap at 2 that no predecessor could fill:
    the ring's 2 and 3 were never taken, and the master waited for them for ever."""
    replica = ControllerProtocol(2, [7, 5, 3, 0, 4, 2, 1, 6], 0)
    replica.start()
    stale = _of_epoch(message(3, 6, range(11, 20)), 4)
    replica.on_log(stale)
    assert 3 in replica.log_queue
    effects = replica.on_log(_of_epoch(message(1, 4, range(1, 6), sender=7), 6))
    assert [type(e).__name__ for e in effects] == ["SendLog", "Unqueued"]
    assert 3 not in replica.log_queue and replica.holds_lognr == 1
    assert replica.missing_lognr is None
    # Given again later: dropped at once, neither forwarded nor queued.
    assert [type(e).__name__ for e in replica.on_log(stale)] == ["Fenced"]
    replay_all(replica)
    # The ring's own 2 and 3 are taken (the number is no longer counted as received).
    assert sends(replica.on_log(_of_epoch(message(3, 4, range(8, 10)), 6))) == [(1, 3, False)]
    assert sends(replica.on_log(_of_epoch(message(2, 4, range(6, 8)), 6))) == [(1, 2, False)]
    assert replica.lognr == 2 and replica.state is State.REPLAY
    replay_all(replica)
    assert (replica.lognr, replica.reqnr) == (3, 9)


def test_a_new_master_goes_active_past_a_replaced_framings_message_and_word() -> None:
    """--lose-master seed 1219, at the new master 4: it rejoined with its handover message
    (1, epoch 6) and was then given the replaced framing's 3 (epoch 4) and told that
    its predecessor holds up to 3. Neither is the ring's; it goes ACTIVE at 1."""
    master = ControllerProtocol(4, [7, 5, 3, 0, 4, 2, 1, 6], 0)
    master.start()
    master.on_granted(6)
    master.on_log(_of_epoch(message(1, 4, range(1, 6), handover=True, sender=7), 6))
    replay_all(master)
    assert [type(e).__name__ for e in master.on_log(_of_epoch(message(3, 6, [11]), 4))] == [
        "Fenced"
    ]
    assert master.on_sync(3, 4) == [ConnectDrone()]
    assert (master.state, master.lognr, master.reqnr) == (State.ACTIVE, 1, 5)


def test_seen_numbers_forget_a_number_below_or_above_the_watermark() -> None:
    seen = SeenNumbers()
    for number in (1, 2, 3, 4, 6):
        seen.add(number)
    seen.discard(6)
    assert seen.upto == 4 and 6 not in seen
    seen.discard(3)
    assert seen.upto == 2 and 3 not in seen and 4 in seen
    seen.add(3)
    assert seen.upto == 4 and len(seen) == 0


def test_the_ring_hello_makes_a_sender_give_a_renumbered_top_message_again() -> None:
    assert resend_after(5, 2, 4) == 4  # ours is newer: give message 5 too
    assert resend_after(5, 4, 4) == 5
    assert resend_after(5, 0, 4) == 5  # a receiver that does not say its epoch
    assert resend_after(5, 2, None) == 5  # we do not hold 5
    p = started(1, [0, 1, 2], 2**20)
    queued = message(3, 0, [3])
    queued.epoch = 2
    p.on_log(queued)
    assert p.epoch_of(3) == 2 and p.epoch_of(7) == 0


def test_a_queued_message_is_replaced_by_the_rings_of_a_newer_epoch() -> None:
    p = started(1, [0, 1, 2], 2**20)
    stale = message(2, 0, [2])
    stale.epoch = 2
    p.on_log(stale)
    ring = message(2, 0, [3])
    ring.epoch = 3
    assert sends(p.on_log(ring)) == [(2, 2, False)]
    assert p.log_queue[2].epoch == 3


def test_a_handover_message_not_handled_is_kept_for_a_rejoin() -> None:
    p = started(1, [0, 1, 2], 2**20)
    ours = message(1, 0, [1])
    ours.epoch = 2
    p.on_log(ours)
    handover = message(1, 1, [1, 2], handover=True, sender=2)
    handover.epoch = 4
    assert [type(e).__name__ for e in p.on_log(handover)] == ["Diverged"]
    later = message(3, 1, [3], handover=True, sender=0)
    later.epoch = 5
    p.on_log(later)
    assert [m.lognr for m in p.kept_for_rejoin()] == [3, 1]


def test_an_old_masters_handover_message_the_ring_went_past_is_held_and_still_forwarded() -> None:
    old = started(0, [0, 1, 2, 3], 2**20)
    old.on_reply(entry(1))
    old.on_handover_notice(2, epoch=2)  # handover message 1 to controller 2
    assert old.holds_lognr == 0
    past = message(2, 2, [2])
    past.epoch = 2  # the new master's next message, before ours came back
    old.on_log(past)
    assert old.holds_lognr == 2 and not old._received.above
    back = message(1, 2, [1])
    back.epoch = 2
    assert sends(old.on_log(back)) == [(1, 1, False)]  # on its way round, as before
    assert old.on_log(back) == []  # once


def test_a_cooperative_grant_waits_for_its_handover_message() -> None:
    new = started(1, [0, 1, 2], 2**20)
    new.on_log(message(1, 0, [1]))
    replay_all(new)
    new.on_sync(1)
    new.on_granted(3)  # before the handover message of epoch 3 came
    assert new.state is State.PASSIVE and not new.caught_up
    handover = message(2, 1, [2], handover=True, sender=0)
    handover.epoch = 3
    new.on_log(handover)
    replay_all(new)
    assert new.state is State.ACTIVE
    taker = started(2, [0, 1, 2], 2**20)
    taker.on_granted(4, takeover=True)  # a takeover owes no handover message
    assert taker.state is State.ACTIVE


def test_a_message_the_predecessor_holds_and_never_sends_is_a_gap() -> None:
    p = started(1, [0, 1, 2], 2**20)
    assert p.missing_lognr is None
    p.on_sync(2)  # it holds 2, and 2's origin is us: the ring will not forward it to us
    assert p.missing_lognr == 1
    p.on_log(message(1, 2, [1]))
    replay_all(p)
    assert p.missing_lognr == 2


@pytest.mark.parametrize("reply_bytes", [0, 1, 100, 127, 128, 16_250, 16_384, 2_097_000, 2**21])
def test_entry_size_is_what_the_entry_adds_to_a_log_message(reply_bytes: int) -> None:
    """Computed from the entry's own size (tag + varint length), not measured on a copy;
    around every varint length boundary it is what a one-entry LogMessage measures."""
    entry = ring_pb2.LogEntry(reqnr=7, method="/m", reply=b"x" * reply_bytes)
    assert entry_size(entry) == ring_pb2.LogMessage(entries=[entry]).ByteSize()


# -- --lose-master seeds 2000-3999 that stalled ------------------------------------------


def framed(
    lognr: int,
    origin: int,
    reqnrs: range | list[int],
    epoch: int,
    handover: bool = False,
    sender: int = -1,
) -> ring_pb2.LogMessage:
    m = message(lognr, origin, reqnrs, handover=handover, sender=sender)
    m.epoch = epoch
    return m


def test_a_refusal_fences_in_the_newest_takeovers_epoch_and_a_later_handover_is_kept() -> None:
    """Seeds 2969, 3704: master 2, cut off, was taken over in epoch 2; the role came back
    to it by a handover message of epoch 5, and the drone handed over from it to 4 in
    epoch 6 at once. Refused (its Connect names the epoch-1 mastership), it rejoins: its
    fresh self must keep the handover message of epoch 5, else 4 waits for ever."""
    from baton.controller.core import DroneRefusal

    refusal = DroneRefusal(master=4, epoch=6, after_reqnr=6, taken_over=True, takeover_epoch=2)
    assert refusal.fencing_epoch == 2
    assert DroneRefusal(master=4, epoch=6, after_reqnr=6).fencing_epoch == 6
    p = started(2, [2, 3, 4], 2**20, initial_master=2)
    p.on_log(framed(2, 1, [1], 5, handover=True, sender=1))  # queued: 1 is missing
    p.on_fenced(refusal.fencing_epoch)
    assert [m.lognr for m in p.kept_for_rejoin()] == [2]


def test_a_handover_message_the_ring_went_past_in_a_newer_epoch_makes_no_master() -> None:
    """Seed 3747: a fresh controller is given again (unacknowledged, re-sent) the handover
    message of epoch 4 that made it master before; the ring's log goes on in epoch 6
    (a takeover after its own handover). It must not take the role: ACTIVE in epoch 4,
    it was fenced, rejoined and given the message again, for ever."""
    p = started(2, [0, 2, 5], 2**20, initial_master=0)
    p.on_log(framed(1, 0, [1], 1))
    p.on_log(framed(2, 2, [2], 4, handover=True, sender=0))
    p.on_log(framed(3, 0, [3], 6))
    replay_all(p)
    p.on_sync(3)
    assert not p.master and p.state is State.PASSIVE
    # It never acted in epoch 4: its log is the ring's, and its Connect names no
    # mastership (seed 1241: else fenced when the drone later made it taker).
    assert p.log_mastership_epoch == 0


def test_a_predecessors_sync_frame_of_a_newer_framing_below_our_top_makes_us_rejoin() -> None:
    """Seed 2791: 5 held the lost master's messages 3-7 (epoch 1); its predecessor holds
    the taker's message 3 (epoch 2) and nothing above it, so it gives 5 nothing. Its sync
    frame says so: 5 diverged, and must rejoin before it takes over on that framing."""
    p = started(5, [6, 5, 4], 2**20, initial_master=6)
    for lognr in range(1, 8):
        p.on_log(framed(lognr, 6, [lognr], 1))
    replay_all(p)
    effects = p.on_sync(3, 2)
    assert [type(e).__name__ for e in effects] == ["Diverged"]
    assert p.on_sync(3, 1) == []  # the same framing


def test_a_taker_drops_the_lost_masters_messages_queued_beyond_a_gap() -> None:
    """Seeds 2034, 3276: the lost master's message 3 died with it, its message 4 reached
    the taker and was queued. The taker holds 2 and gets every reply above from the
    drone: it drops 4 and goes ACTIVE, where it waited for 3 for ever."""
    p = started(1, [0, 1], 2**20)
    p.on_log(framed(1, 0, [1], 1))
    p.on_log(framed(2, 0, [2], 1))
    p.on_log(framed(4, 0, [4], 1))
    replay_all(p)
    assert p.on_granted(2, takeover=True, watermark_reqnr=0) == []
    assert p.state is State.PASSIVE  # 3 may be on its way: the gap repair asks first
    effects = p.give_up_gap()  # the repair did not bring it (ControllerCore.gap_due)
    assert [(type(e).__name__, getattr(e, "lognr", None)) for e in effects] == [
        ("Unqueued", 4),
        ("ConnectDrone", None),
    ]
    assert p.state is State.ACTIVE and not p.log_queue and 4 not in p._received


def test_a_taker_gives_up_a_gap_its_predecessor_promised_of_the_lost_masters_epoch() -> None:
    """The predecessor said, after the takeover, that it held the lost master's messages
    3-4 (epoch 1), then was fenced and rejoined with nothing: its word cannot be kept.
    A word about the framing the gap gives up goes with it (it kept the taker from
    being caught up for ever: ``--lose-master`` seed 14453)."""
    p = started(1, [0, 1], 2**20)
    p.on_log(framed(1, 0, [1], 1))
    p.on_log(framed(2, 0, [2], 1))
    p.on_log(framed(4, 0, [4], 1))
    replay_all(p)
    assert p.on_granted(2, takeover=True, watermark_reqnr=0) == []
    p.on_sync(4, 1)  # the lost master holds 3-4; 3 never reaches us
    assert not p.caught_up
    effects = p.give_up_gap()
    assert [(type(e).__name__, getattr(e, "lognr", None)) for e in effects] == [
        ("Unqueued", 4),
        ("ConnectDrone", None),
    ]
    assert p.state is State.ACTIVE and p.caught_up


def test_a_takers_gap_give_up_keeps_the_drones_watermark() -> None:
    """Giving up the lost master's words does not give up the drone's: a taker that
    does not hold every request up to the watermark stays PASSIVE."""
    p = started(1, [0, 1], 2**20)
    p.on_log(framed(1, 0, [1], 1))
    p.on_log(framed(4, 0, [4], 1))
    replay_all(p)
    p.on_granted(2, takeover=True, watermark_reqnr=3)
    p.on_sync(4, 1)
    assert [type(e).__name__ for e in p.give_up_gap()] == []
    assert p.state is State.PASSIVE


def test_a_replica_does_not_give_up_a_gap() -> None:
    p = started(1, [0, 1, 2], 2**20)
    p.on_log(framed(1, 0, [1], 1))
    p.on_log(framed(3, 0, [3], 1))
    replay_all(p)
    assert p.give_up_gap() == [] and 3 in p.log_queue


def test_a_mastership_handed_over_is_not_the_log_we_connect_with() -> None:
    """Seed 2572: 1 handed over to 0 in epoch 3 (its handover message came back round),
    then was given the role in epoch 4 while cut off, taken over in epoch 5 before it
    knew, and granted it back by takeover in epoch 6. Its Connect named its epoch-2
    mastership, which the drone took for the one taken over: the taker, which held the
    ring's log, rejoined with nothing, and nobody held the requests below the watermark."""
    from baton.drone.sequencer import Sequencer

    p = started(1, [0, 1], 2**20, initial_master=0)
    p.on_log(framed(1, 0, [1], 2, handover=True))
    replay_all(p)
    p.on_granted(2)
    assert p.state is State.ACTIVE and p.log_mastership_epoch == 2
    p.on_reply(entry(2))
    p.on_handover_notice(0, epoch=3)
    assert p.log_mastership_epoch == 2  # our handover message has not come back
    p.on_log(framed(3, 0, [3], 3))  # the ring went on past it
    replay_all(p)
    assert p.log_mastership_epoch == 0

    seq = Sequencer([0, 1], initial_master=0)
    seq.switch(1, drone_pb2.HANDOVER_TRIGGER_SCRIPT, now=1.0)  # epoch 2
    seq.switch(0, drone_pb2.HANDOVER_TRIGGER_SCRIPT, now=2.0)  # epoch 3
    seq.switch(1, drone_pb2.HANDOVER_TRIGGER_SCRIPT, now=3.0)  # epoch 4, unheard
    seq.switch(0, drone_pb2.HANDOVER_TRIGGER_LOST, now=4.0, takeover=True)  # epoch 5
    seq.switch(1, drone_pb2.HANDOVER_TRIGGER_LOST, now=5.0, takeover=True)  # epoch 6
    seq.admit_connect(1, p.log_mastership_epoch)  # granted, not fenced
    with pytest.raises(StatusError):
        seq.admit_connect(1, 2)  # what it said before


def test_a_fenced_master_keeps_the_messages_that_went_round_the_ring() -> None:
    """Seed 3818: 0 flushed message 1 (requests 1-10), which went round the ring (1 said
    it holds it, and the drone let go of those replies); 1 restarted with nothing and
    took over. 0, fenced, rejoined with nothing: nobody held requests 1-10 and the taker
    waited for ever. A fenced controller keeps what went round; a diverged one nothing."""
    p = started(0, [0, 1], 0)
    p.on_reply(entry(1))  # flushed at once: message 1
    p.on_reply(entry(2))  # message 2, not acknowledged yet
    p.on_sync(1)  # 1 holds message 1
    assert p.watermark_reqnr == 1 and p.acked_lognr == 1
    assert p.kept_when_fenced() == 0  # not fenced
    p.on_fenced(2)
    assert p.kept_when_fenced() == 1
    # In a longer ring the word may come from one routing around the taker (seed 973).
    q = started(0, [0, 1, 2], 0)
    q.on_reply(entry(1))
    q.on_sync(1)
    q.on_fenced(2)
    assert q.acked_lognr == 1 and q.kept_when_fenced() == 0


def test_a_word_above_our_top_of_a_newer_mastership_moves_no_watermark() -> None:
    """--policy nearest seed 12952 (a ring of two): taker 1 (epoch 2) flushed messages 1-2,
    the last a give-up of request 12 made while cut off; 0 restarted with nothing and took
    over (epoch 3), framing requests 1-11 anew in messages 1-3. Its word "I hold message 3
    of epoch 3" counted as 1's messages 1-2 gone round the ring: fenced, 1 kept them, its
    program saw the give-up where the master's saw a reply, and it rejoined for ever. Such
    a word is built on ours by a handover or framed anew by a takeover: it proves nothing."""
    p = started(0, [0, 1], 0)
    p.on_reply(entry(1))
    p.on_reply(entry(2))  # messages 1-2 of epoch 1
    p.on_sync(3, holds_epoch=2)
    assert p.acked_lognr == 0 and p.watermark_reqnr == 0
    p.on_fenced(2)
    assert p.kept_when_fenced() == 0
    # Of our own mastership, above our top (a handover's target went on in our epoch's
    # numbering only after handling ours): it holds ours.
    q = started(0, [0, 1], 0)
    q.on_reply(entry(1))
    q.on_sync(2, holds_epoch=1)
    assert q.acked_lognr == 1 and q.watermark_reqnr == 1


def test_a_master_that_hands_over_looks_at_what_it_queued_while_active() -> None:
    """--lose-master --prepared seed 4860: master 1, ACTIVE in epoch 3, queued the ring's
    messages 14-15 of a takeover's epoch 5, which framed request 13 anew after message 13;
    then the drone's late notice of an epoch-4 handover came, and 1 handed over as message
    14. PASSIVE, it never looked at its queue again: the takeover's 15 waited behind our
    14 for ever. It looks at once, and rejoins on the diverged framing."""
    p = started(0, [0, 1, 2], 0)
    p.on_reply(entry(1))  # message 1 of epoch 1
    theirs = [_of_epoch(message(2, 2, [2]), 3), _of_epoch(message(3, 2, [3]), 3)]
    theirs[0].after_epoch, theirs[1].after_epoch = 1, 3
    for m in theirs:
        p.on_log(m)
    assert p.state is State.ACTIVE and sorted(p.log_queue) == [2, 3]
    effects = p.on_handover_notice(1, epoch=2)
    assert sends(effects) == [(1, 2, True)]
    assert [e for e in effects if isinstance(e, Diverged)] == [Diverged(2, 2, 3)]


def test_an_empty_handover_message_handing_the_role_back_to_an_active_master_is_handled() -> None:
    """--policy nearest seed 1866: master 5, ACTIVE in epoch 3, never heard that the drone
    took the role over (epoch 4) and its taker handed it back (epoch 5) with nothing
    framed in between. The handover message, next to our top, stayed queued for ever;
    the ring took it as that number, so our own message numbered like it would be taken
    for one seen. It is handled, as a PASSIVE controller handles it."""
    p = started(0, [0, 1], 0)
    p.on_reply(entry(1))  # message 1, epoch 1
    back = ring_pb2.LogMessage(
        lognr=2, origin=0, sender=1, handover=True, epoch=3, after_reqnr=1, after_epoch=1
    )
    p.on_log(back)
    assert (p.state, p.lognr, p.epoch, dict(p.log_queue)) == (State.ACTIVE, 2, 3, {})
    flushed = p.on_reply(entry(2))  # our next message is numbered after it, in its epoch
    assert sends(flushed) == [(1, 3, False)]
    assert [e.message.epoch for e in flushed if isinstance(e, SendLog)] == [3]
    # One with entries went on without us (the core fences us on it): left queued.
    q = started(0, [0, 1], 0)
    q.on_reply(entry(1))
    went_on = ring_pb2.LogMessage(
        lognr=2, origin=0, sender=1, handover=True, epoch=3, after_reqnr=1, after_epoch=1
    )
    went_on.entries.append(entry(2))
    q.on_log(went_on)
    assert (q.lognr, q.epoch, sorted(q.log_queue)) == (1, 1, [2])


def test_in_a_longer_ring_a_fenced_master_keeps_what_the_drone_took_as_let_go() -> None:
    """--lose-master seed 13253: in a ring of three, what went round by the predecessor's
    word may have skipped a taker that lacks it, so that alone keeps nothing; but the
    requests up to a watermark the drone took (a call that carried it answered, or the
    drone's watermark at the takeover, as its refusal or notice says) are never framed
    anew by any later master, so a fenced master keeps its messages up to it (the only
    copy left when the others restarted or rejoined with nothing)."""
    q = started(0, [0, 1, 2], 0)
    for reqnr in (1, 2, 3):
        q.on_reply(entry(reqnr))  # messages 1-3, flushed at once
    q.on_sync(2)  # the predecessor holds messages 1-2: the watermark is request 2
    assert q.watermark_reqnr == 2 and q.acked_lognr == 2
    q.drone_took_watermark(1)  # a call carrying watermark 1 was answered
    q.on_fenced(2)
    assert q.kept_when_fenced() == 1
    r = started(0, [0, 1, 2], 0)
    for reqnr in (1, 2, 3):
        r.on_reply(entry(reqnr))
    r.on_sync(2)
    r.on_fenced(2, watermark=2)  # the drone's watermark at the takeover
    assert r.kept_when_fenced() == 2  # message 3 is above it: the taker framed it anew
    assert started(0, [0, 1, 2], 0).kept_when_fenced() == 0


def test_a_fenced_master_keeps_its_messages_up_to_the_one_its_taker_built_on() -> None:
    """--lose-master --prepared seed 14590 (a ring of two): taker 0 held the fenced
    master 1's log up to message 10 and was then lost for good; 1, fenced, kept nothing
    of it (none of it had gone round from 1, nor was below a watermark 1 was told), and
    the drone had let go of the replies. The taker's first Connect said the message it
    built on; the drone's refusal says it, and a fenced master that holds that message
    of that epoch keeps its messages up to it, in any ring."""
    for ring in ([0, 1], [0, 1, 2]):
        q = started(0, ring, 0)
        for reqnr in (1, 2, 3):
            q.on_reply(entry(reqnr))  # messages 1-3 of epoch 1, none gone round
        assert q.epoch_of(2) == 1
        q.on_fenced(2, taker_holds=(2, 1))
        assert q.kept_when_fenced() == 2
    for other in ((2, 5), (7, 1), (0, 0)):  # another message 2, one we lack, not said
        q = started(0, [0, 1], 0)
        for reqnr in (1, 2, 3):
            q.on_reply(entry(reqnr))
        q.on_fenced(2, taker_holds=other)
        assert q.kept_when_fenced() == 0, other


def test_a_fenced_master_keeps_the_takers_messages_it_queued() -> None:
    """--policy seed 882 (a ring of two): master 0, cut off, flushed message 1, which went
    round; 1 took over (epoch 2) and its messages 2-3 came to 0, still ACTIVE, which
    queued them. 1 handed the role back and died, and the drone let go of those replies.
    Fenced (granted by the handover message, its own mastership replaced), 0 kept only
    message 1, and nobody held 2-3. It keeps the taker's lineage after what went round:
    the messages of the takeover's epoch or newer, not its own older ones."""
    p = started(0, [0, 1], 0)
    p.on_reply(entry(1))  # message 1
    p.on_sync(1)
    for lognr in (2, 3):
        p.on_log(_of_epoch(message(lognr, 1, [lognr]), 2))  # queued: we are ACTIVE
    assert p.state is State.ACTIVE and sorted(p.log_queue) == [2, 3]
    p.on_fenced(2)
    assert p.kept_when_fenced() == 3
    # Our own message 2 of epoch 1 after it instead (not acknowledged): only what went
    # round, even with a message of the taker's epoch queued above ours.
    q = started(0, [0, 1], 0)
    q.on_reply(entry(1))
    q.on_sync(1)
    q.on_reply(entry(2))
    q.on_log(_of_epoch(message(3, 1, [3]), 2))
    q.on_fenced(2)
    assert q.kept_when_fenced() == 1


def test_a_master_whose_program_starts_again_keeps_its_log_for_its_fresh_self() -> None:
    """--lose-master seeds 10688, 11795 (a ring of two, controller 0 lost): taker 1's
    program gave up on request 11, whose retained reply a lost master's program acted on;
    the entry is that reply, and the program starts again by a rejoin. The rejoin dropped
    everything, and nobody else held the requests below the drone's watermark: the fresh
    taker waited for them for ever. The master flushes its log, and its fresh self is fed
    every message up to it; a master fenced since keeps what that keeps. A replica keeps
    what it handled: --lose-master --prepared 9935 (a ring of two), the new master of a
    prepared handover, not yet ACTIVE, restarted its program and rejoined with nothing;
    its old master was lost for good, and the drone had let go of the replies."""
    p = started(1, [1, 0], 2**20, initial_master=1)
    p.on_reply(entry(1))
    p.on_reply(entry(2))
    assert sends(p.restart_program()) == [(0, 1, False)]
    assert not p.log and p.kept_history() == 1
    p.on_fenced(2)
    assert p.kept_history() == p.kept_when_fenced() == 0
    replica = started(0, [1, 0], 2**20, initial_master=1)
    replica.on_log(_of_epoch(message(1, 1, [1, 2]), 1))
    replay_all(replica)
    assert replica.restart_program() == [] and replica.kept_history() == 1
    # The fresh self holds the log again and goes ACTIVE on it when granted.
    fresh = ControllerProtocol(1, [1, 0], 2**20)
    fresh.start()
    kept = message(1, 1, [1, 2])
    kept.epoch = 1
    fresh.on_log(kept)
    fresh.on_granted(3, takeover=True, watermark_reqnr=2)
    replay_all(fresh)
    assert fresh.state is State.ACTIVE and fresh.reqnr == 2


def test_a_program_that_starts_again_keeps_a_handover_message_for_the_fresh_self() -> None:
    """--lose-master seed 11002: replica 6's program gave up on request 1, which the log
    holds as served: it starts again by a rejoin. Before the rejoin, the handover message
    that made 6 master came and was handled; it was not kept (not queued), the fresh self
    got only the old master's history copy (no flag), and the drone, which had moved the
    role on to 0 already, waited for ever for 6's handover. Once the program starts
    again, nothing more is handled: the message is queued and kept for the fresh self."""
    p = ControllerProtocol(1, [0, 1, 2], 2**20)
    p.start()
    p.on_sync(0)
    p.on_log(_of_epoch(message(1, 0, [1, 2]), 1))
    assert p.state is State.REPLAY
    p.replay(GET, b"")  # the call the program gave up on: the log says it was served
    assert p.restart_program() == [] and p.kept_history() == 1  # what it handled
    replay_all(p)
    handover = _of_epoch(message(2, 1, [3], handover=True, sender=0), 2)
    p.on_log(handover)
    assert not p.master and p.lognr == 1
    assert p.kept_for_rejoin() == [handover]


def test_a_handover_message_sent_again_to_a_restarted_receiver_gives_no_role_handed_on() -> None:
    """Simulation finding F9: the acknowledgement of handover message 1 (epoch 2) was lost;
    its receiver handed the role on (message 2, epoch 3) and restarted with nothing; the old
    master sent message 1 again, flag set. The ring's message 2 says that mastership is over:
    the restarted receiver does not take it (it went ACTIVE in epoch 2 and, refused, made a
    second message 3 of its own)."""
    p = ControllerProtocol(1, [0, 1, 2], flush_limit=2**20)
    p.start()
    p.on_sync(2)  # the predecessor holds 2
    handover = message(1, 1, [1], handover=True, sender=0)
    handover.epoch = 2
    passed_on = message(2, 2, [2], sender=1)  # our earlier self's handover message to 2
    passed_on.epoch, passed_on.after_reqnr, passed_on.after_epoch = 3, 1, 2
    p.on_log(handover)
    p.on_log(passed_on)
    effects = replay_all(p)
    assert p.lognr == 2 and not p.master and p.state is State.PASSIVE and p.epoch == 0
    assert not any(isinstance(e, ConnectDrone) for e in effects)
    # Handed to us and still ours (the drone's word, or nothing newer): the role is taken.
    q = ControllerProtocol(1, [0, 1, 2], flush_limit=2**20)
    q.on_sync(1)
    q.on_log(handover)
    assert any(isinstance(e, ConnectDrone) for e in replay_all(q)) and q.master


def test_a_handover_message_is_settled_once_the_ring_went_past_it() -> None:
    """Simulation finding F9, the sender's side: a handover message still unacknowledged
    on the direct stream is sent without its flag (``PeerLink.settle_handovers``) once the
    ring went on past it, or it came back."""
    old = started(0, [0, 1, 2, 3], 2**20)
    old.on_reply(entry(1))
    old.on_handover_notice(2, epoch=2)  # handover message 1 to controller 2
    assert not old.handover_settled(1)
    past = message(2, 2, [2])
    past.epoch = 2
    old.on_log(past)
    assert old.handover_settled(1)
    back = started(0, [0, 1, 2, 3], 2**20)
    back.on_reply(entry(1))
    back.on_handover_notice(2, epoch=2)
    home = message(1, 2, [1])
    home.epoch = 2
    back.on_log(home)
    assert back.handover_settled(1)


def test_forward_dest_says_from_the_head_alone_what_on_log_forwards_unchanged() -> None:
    """Cut-through asks ``forward_dest`` on a message's first frame: it must agree with
    what ``on_log`` then does with the whole message, and say None where the message
    would go on changed (a handover message loses its flag)."""
    from baton.controller.ring import head_of

    cases = [
        (message(1, 0, [1]), 2),  # new, from the master: on to the successor
        (message(1, 0, [1]), None),  # seen: a re-send is ignored
        (message(2, 2, [2]), None),  # its origin is our successor: it stops here
        (message(3, 0, [3], handover=True), None),  # forwarded without its flag
    ]
    p = started(1, [0, 1, 2], 0)
    for whole, expected in cases:
        assert p.forward_dest(head_of(whole)) == expected
        forwarded = [dest for dest, _, flag in sends(p.on_log(whole)) if not whole.handover]
        assert forwarded == ([] if expected is None else [expected])
        replay_all(p)
    q = started(1, [0, 1, 2], 0)
    assert sends(q.on_log(_of_epoch(message(1, 0, [1]), 3))) == [(2, 1, False)]
    fenced = _of_epoch(message(2, 0, [2]), 1)  # numbered after a newer mastership's
    assert q.forward_dest(head_of(fenced)) is None
    assert sends(q.on_log(fenced)) == []


def test_a_taker_finds_a_request_it_holds_in_a_framing_a_later_takeover_replaced() -> None:
    """--policy nearest seed 132: master 4, cut off, answered Clock.Now 2 itself (reading
    A) and flushed it to 2 in epoch 1; a takeover that did not hold it (epoch 3) read B
    and brought that to the drone. Made master by takeover (epoch 7), 2 holds 2 up to
    request 2 and said so: it must not build on reading A. The drone's reply brought in
    a newer epoch than our framing, and other, is a replaced framing; the same outcome,
    or one brought in our framing's epoch or before (a give-up of a request the drone
    served, not sent along yet), is the ring's."""
    now = "/baton.v1.Clock/Now"
    taker = ControllerProtocol(2, [4, 2, 0, 3, 1], 0)
    taker.start()
    cut_off = _of_epoch(message(1, 4, [1]), 1)
    cut_off.entries.append(entry(2, now, reply=b"reading A"))
    taker.on_log(cut_off)
    taker.on_granted(7, takeover=True)
    taker.replay(GET, b"")
    taker.replay(now, b"")
    assert (taker.state, taker.held_reqnr) == (State.ACTIVE, 2)

    def kept(reply: bytes, epoch: int, reqnr: int = 2) -> drone_pb2.RetainedReply:
        method = now if reqnr == 2 else GET
        return drone_pb2.RetainedReply(
            reqnr=reqnr,
            method=method,
            request_digest=request_digest(method, b""),
            reply=reply,
            epoch=epoch,
        )

    first = kept(b"reply 1", 1, reqnr=1)
    replaced = kept(b"reading B", 3)
    assert taker.replaced_framing([first, replaced]) == ReplacedFraming(2, 1, 1, 3)
    assert taker.replaced_framing([first, kept(b"reading A", 3)]) is None  # the same
    assert taker.replaced_framing([kept(b"reading B", 1)]) is None  # ours is as new
    assert taker.replaced_framing([kept(b"reading B", 3, reqnr=3)]) is None  # not held


def test_a_taker_whose_framing_was_replaced_refuses_it_and_frames_anew() -> None:
    """--lose-master seed 3166: master 2's framing (epoch 2) holds its give-up of request
    3; a taker (epoch 5) executed 3 and was lost before its messages left, so the ring
    holds only the replaced framing. Taker 4 (epoch 6) finds it replaced, and its fresh
    self refuses it from the message that holds 3 on (and its holder's word that it
    holds it): it holds what precedes it, goes ACTIVE on the drone's word, and its own
    message 3, of epoch 6, is the one that replaces the old on the ring. Rejoining
    with nothing alone, it was given the old framing again and rejoined for ever."""
    ring = [_of_epoch(message(n, 1, [n]), 2) for n in (1, 2, 3)]
    taker = ControllerProtocol(4, [1, 3, 4, 2], 0)
    taker.start()
    for m in ring:
        taker.on_log(m)
    taker.on_sync(3, 2)
    replay_all(taker)
    taker.on_granted(6, takeover=True, watermark_reqnr=2)
    executed = drone_pb2.RetainedReply(
        reqnr=3, method=GET, request_digest=request_digest(GET, b""), reply=b"done", epoch=5
    )
    replaced = taker.replaced_framing([executed])
    assert replaced == ReplacedFraming(reqnr=3, lognr=3, ours_epoch=2, epoch=5)

    fresh = ControllerProtocol(4, [1, 3, 4, 2], 0)
    fresh.start()
    fresh.refuse_replaced(replaced)
    fresh.on_sync(3, 2)  # the predecessor holds 3, of the replaced framing
    assert [sends(fresh.on_log(m)) for m in ring] == [[(2, 1, False)], [(2, 2, False)], []]
    assert (fresh.holds_lognr, fresh.catch_up_to) == (2, 0)
    assert sends(fresh.on_log(_of_epoch(message(4, 1, [4]), 2))) == []  # and what follows
    fresh.on_granted(6, takeover=True, watermark_reqnr=2)
    replay_all(fresh)
    assert fresh.state is State.ACTIVE
    effects = fresh.on_reply(ring_pb2.LogEntry(reqnr=3, method=GET, reply=b"done"))
    assert [(m.lognr, m.epoch) for m in (e.message for e in effects if isinstance(e, SendLog))] == [
        (3, 6)
    ]
    # A framing newer than the replaced one is not refused: it may be the drone's.
    other = ControllerProtocol(4, [1, 3, 4, 2], 0)
    other.start()
    other.refuse_replaced(replaced)
    other.on_log(ring[0])
    other.on_log(ring[1])
    assert sends(other.on_log(_of_epoch(message(3, 1, [3]), 5))) == [(2, 3, False)]


# -- --policy seeds that broke same-replies (2026-11-27) -------------------------------


def test_a_predecessors_word_for_our_number_in_an_older_framing_does_not_move_the_watermark() -> (
    None
):
    """--policy predictive seed 408 (nearest 1122 and 3283 the same): taker 0 (epoch 3)
    framed Clock request 1 in its message 1; its predecessor 5 still held the lost 2's
    message 1 (epoch 2, another reading) and said so. 0 took that for its own message 1
    and gave the drone watermark 1: the drone let its reply go, and 5, taking over later
    on the older reading, found nothing retained to compare it with and built on it.
    The ring's word (the same number in our epoch) moves the watermark as before."""
    master = started(0, [0, 1, 5], 0)
    master.on_granted(3, takeover=True)
    master.on_reply(entry(1))  # flushes message 1 of epoch 3
    master.on_reply(entry(2))  # and 2
    assert master.on_sync(1, 2) == []  # 5's message 1 is of epoch 2
    assert master.watermark_reqnr == 0 and master.catch_up_to == 1
    master.on_sync(2, 3)
    assert master.watermark_reqnr == 2


def test_a_queued_message_of_a_newer_mastership_fences_a_master_once_cut_off() -> None:
    """--policy nearest seed 2921: master 1 flew out of range; the drone made 0 master by
    takeover in a newer epoch, and 0's next message came while 1's Connect stream still looked up
    (a silent link, not yet found by keepalive), so the ring's fence did not apply then.
    Queued, the message was never looked at again and 1 stayed ACTIVE for ever. The
    core asks ``went_on_in_queue`` after every event while cut off (``ControllerCore.ready``)."""
    p = started(1, [0, 1], 2**20, initial_master=1)
    p.on_reply(entry(1))
    p.on_reply(entry(2))  # unflushed: the log never left us
    assert p.went_on_in_queue() is None
    taker = framed(2, 0, [1, 2], 2)  # the taker's second message (its first on its way)
    p.on_log(taker)
    assert 2 in p.log_queue and p.state is State.ACTIVE
    assert p.went_on_in_queue() == taker
    p.on_handover_notice(0, epoch=2)  # not ACTIVE: nothing of ours is held back
    assert p.went_on_in_queue() is None


# -- --policy nearest seed 48: a master's fresh self and its earlier self's message -----


def test_a_master_that_flushed_and_rejoins_gives_its_mastership_up_to_its_fresh_self() -> None:
    """--policy nearest seed 48: taker 4 (epoch 15) flushed its message 12 on a framing it
    then gave up (it diverged and rejoined with nothing). Its fresh self tells the drone,
    which grants it a new epoch: regranted 15, its messages could not be told apart from
    that message 12. A master that flushed nothing in its epoch, or was fenced, or whose
    program starts again (its log is the ring's), gives nothing up."""
    p = started(4, [4, 0, 3], 2**20)
    p.on_log(framed(1, 0, [1], 14))
    replay_all(p)
    p.on_granted(15, takeover=True)
    assert p.state is State.ACTIVE and p.mastership_given_up() == 0  # nothing flushed
    p.on_reply(entry(2))
    p.on_mission_done()  # flushes message 2 of epoch 15
    assert p.mastership_given_up() == 15
    fresh = ControllerProtocol(4, [4, 0, 3], 2**20)
    fresh.given_up_epoch = p.mastership_given_up()
    assert fresh.mastership_given_up() == 15  # said again if the fresh self rejoins too
    restarting = started(4, [4, 0, 3], 0, initial_master=4)
    restarting.on_reply(entry(1))
    restarting.restart_program()
    assert restarting.mastership_given_up() == 0
    fenced = started(4, [4, 0, 3], 0, initial_master=4)
    fenced.on_reply(entry(1))
    fenced.on_fenced(2)
    assert fenced.mastership_given_up() == 0


def test_a_newer_masters_word_drops_an_older_message_queued_above_its_top() -> None:
    """--policy nearest seed 48: every controller held the ring's messages 1-9 (epoch 14)
    and the earlier self's message 12 (epoch 15) queued above a gap nobody could fill; the
    fresh master (epoch 16) logged nothing more, so no message of its epoch ever dropped
    it. Its sync frame says it is ACTIVE in epoch 16 holding 9: the successor drops 12, and
    says so to its own successor. A word of the queued message's own epoch drops nothing."""
    master = started(4, [4, 0, 3], 2**20)
    for lognr in range(1, 10):
        master.on_log(framed(lognr, 0, [lognr], 14))
    replay_all(master)
    master.on_log(framed(12, 4, [12], 15))
    master.on_granted(16, takeover=True)
    assert [type(e).__name__ for e in master.give_up_gap()] == ["Unqueued", "ConnectDrone"]
    assert master.state is State.ACTIVE and master.master_word == (16, 9)
    p = started(0, [4, 0, 3], 2**20, initial_master=4)
    for lognr in range(1, 10):
        p.on_log(framed(lognr, 3, [lognr], 14))
    replay_all(p)
    p.on_log(framed(12, 4, [12], 15))
    assert p.missing_lognr == 10 and p.master_word == (0, 0)
    assert p.on_sync(9, 14, 15, 9) == [] and 12 in p.log_queue  # not older than its epoch
    effects = p.on_sync(9, 14, *master.master_word)
    assert [(type(e).__name__, getattr(e, "lognr", None)) for e in effects] == [("Unqueued", 12)]
    assert not p.log_queue and 12 not in p._received and p.missing_lognr is None
    assert p.master_word == (16, 9)
    p.on_sync(9, 14, 15, 8)  # an older word is not relayed
    assert p.master_word == (16, 9)


def test_a_mastership_handed_back_owes_no_handover_message_of_the_grant_before() -> None:
    """A cooperative grant owes us its epoch's handover message; once that came, or a
    newer handover message made us master, nothing is owed (``Mastership.problems``,
    rule 4). Handed back to an ACTIVE master (``_take_handed_back``), its new epoch
    owes nothing either."""
    p = started(0, [0, 1], 0, initial_master=1)
    p.on_granted(2)  # cooperative: its handover message is owed
    assert p.mastership.owed == 2
    p.on_log(ring_pb2.LogMessage(lognr=1, origin=1, sender=1, handover=True, epoch=2))
    assert p.state is State.ACTIVE
    back = ring_pb2.LogMessage(
        lognr=2, origin=0, sender=1, handover=True, epoch=5, after_reqnr=0, after_epoch=2
    )
    p.on_log(back)
    assert (p.state, p.epoch) == (State.ACTIVE, 5)
    assert p.mastership.problems() == []


def test_a_role_handed_back_in_another_framing_of_our_requests_means_we_must_rejoin() -> None:
    """An ACTIVE master that never heard of a takeover between (cut off, it logged
    give-ups) is handed the role back by the taker's handover message, which follows
    the taker's framing of the same requests (``after_epoch``): ours was replaced, so
    the message is not taken as ours to continue (``_take_handed_back``); we rejoin."""
    p = started(0, [0, 1], 0)
    p.on_reply(entry(1))
    p.on_reply(entry(2))  # messages 1 and 2, epoch 1
    back = ring_pb2.LogMessage(
        lognr=3, origin=0, sender=1, handover=True, epoch=3, after_reqnr=2, after_epoch=2
    )
    effects = p.on_log(back)
    assert [e for e in effects if isinstance(e, Diverged)] == [Diverged(2, 1, 2)]
    assert p.epoch == 1


def _handover_after(reqnr: int, m: ring_pb2.LogMessage) -> ring_pb2.LogMessage:
    m.after_reqnr = reqnr
    return m


def test_a_queued_message_that_follows_fewer_requests_than_we_hold_is_dropped() -> None:
    """A message cannot follow our log if it follows fewer requests than our log holds
    already: within one lineage a message numbered above ours follows at least every
    request ours holds. Such a message is of a framing that left ours before (the same
    replies numbered otherwise by a takeover's taker), and the message between it and
    ours that it waits for exists only in that framing: queued, it stood for a gap no
    predecessor could fill, repaired every few seconds for ever."""
    replica = started(1, [0, 1, 2], 2**20)
    replica.on_log(_of_epoch(message(1, 0, range(1, 8)), 4))
    replica.on_log(_handover_after(7, _of_epoch(message(2, 0, []), 7)))
    replay_all(replica)
    assert (replica.lognr, replica.held_reqnr) == (2, 7)
    # Message 4 of the other framing: it follows request 5 (its 3 holds 4-5).
    other = _of_epoch(message(4, 2, [6, 7]), 9)
    effects = replica.on_log(other)
    assert "Unqueued" in [type(e).__name__ for e in effects]
    assert replica.log_queue == {} and replica.missing_lognr is None
    # The ring's own 3 and 4 are taken after it.
    replica.on_log(_of_epoch(message(3, 0, [8]), 9))
    replica.on_log(_of_epoch(message(4, 0, [9]), 9))
    replay_all(replica)
    assert (replica.lognr, replica.held_reqnr) == (4, 9)


def test_a_queued_message_is_dropped_once_the_log_below_it_holds_more_than_it_follows() -> None:
    """The same rule when the other framing's message came first, while we held less:
    it is dropped once the ring's messages below it are handled."""
    replica = started(1, [0, 1, 2], 2**20)
    replica.on_log(_of_epoch(message(4, 2, [6, 7]), 9))
    assert 4 in replica.log_queue
    replica.on_log(_of_epoch(message(1, 0, range(1, 8)), 4))
    replay_all(replica)
    replica.on_log(_handover_after(7, _of_epoch(message(2, 0, []), 7)))
    assert replica.log_queue == {} and replica.missing_lognr is None
