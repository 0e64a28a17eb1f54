"""The controller's pure core for its drone session: the drone's word in, effects out
(no sockets, no tasks): the decisions node.py and the simulation both carry out."""

from __future__ import annotations

from helpers.protocol import started

from baton.controller.core import (
    CLOCK_SLEEP,
    PREPARE_GRACE_S,
    Answer,
    Arm,
    AskClock,
    AskDrone,
    ControllerCore,
    Disarm,
    DroneRefusal,
    Fail,
    KeepMastership,
    Note,
    Persist,
    Reconnect,
    Record,
    Rejoin,
    RepairGap,
    RingSight,
    RouteTo,
    SayWord,
    Seen,
    SendCatchUp,
    Timer,
)
from baton.controller.link_core import SyncWord
from baton.controller.protocol import DisconnectDrone, Diverged, SendLog, State
from baton.digest import request_digest
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2, ring_pb2

GET = "/baton.v1.Mobility/GetPosition"


def master(cut_through: bool = True) -> ControllerCore:
    """Controller 0 of ring 0 -> 1 -> 2, ACTIVE master in epoch 1."""
    core = ControllerCore(started(0, [0, 1, 2], 0), cut_through)
    assert core.protocol.state is State.ACTIVE
    return core


def kinds(effects: list) -> list[type]:
    return [type(effect) for effect in effects]


def prepare(target: int, epoch: int, timeout_s: float) -> drone_pb2.PrepareHandover:
    """The drone's word that it prepares a handover to ``target`` (no bound on the bytes)."""
    return drone_pb2.PrepareHandover(target=target, epoch=epoch, timeout_s=timeout_s)


def notice(
    new_master: int, after_reqnr: int, epoch: int, takeover_epoch: int = 0
) -> drone_pb2.HandoverNotice:
    """A cooperative handover's notice on the Connect stream."""
    return drone_pb2.HandoverNotice(
        new_master=new_master, after_reqnr=after_reqnr, epoch=epoch, takeover_epoch=takeover_epoch
    )


def test_a_handover_notice_sends_the_log_and_with_cut_through_the_catch_up_first() -> None:
    core = master()
    effects = core.handover_notice(2, 0, 2)
    assert kinds(effects) == [Record, Note, SendCatchUp, DisconnectDrone, SendLog]
    send = effects[-1]
    assert isinstance(send, SendLog) and send.dest == 2 and send.message.handover
    assert core.protocol.state is State.PASSIVE
    assert kinds(master(cut_through=False).handover_notice(2, 0, 2)) == [
        Record,
        Note,
        DisconnectDrone,
        SendLog,
    ]


def test_a_stale_handover_notice_hands_nothing_over_and_sends_no_catch_up() -> None:
    """A notice of a switch before our mastership (epoch 1 while we are master in 3): the
    runtime ignored it while the simulation's copy still sent the catch-up."""
    core = master()
    core.protocol.on_granted(3)
    effects = core.handover_notice(2, 0, 1)
    note = effects[0]
    assert (
        kinds(effects) == [Note]
        and isinstance(note, Note)
        and note.text == "stale handover notice ignored"
    )
    assert core.protocol.state is State.ACTIVE


def test_a_notice_after_a_takeover_that_replaced_our_log_fences_us() -> None:
    """ACTIVE in epoch 1, a notice of a switch out of epoch 4 whose drone took over in
    epoch 3: the takeover framed our unflushed requests anew, so handing our log over
    would put a second framing of them on the ring; we rejoin with nothing instead.
    Without a takeover since our mastership (back-to-back handovers), the log is the
    ring's and goes to the new master."""
    replaced = master().stream_notice(notice(2, 2, 5, takeover_epoch=3))
    assert kinds(replaced) == [Record, Note, DisconnectDrone, Rejoin]
    assert SendLog not in kinds(replaced)
    handed = master().stream_notice(notice(2, 2, 5))
    assert kinds(handed)[-1] is SendLog
    older = master()
    older.protocol.on_granted(3)  # the takeover that made us master: our own log
    assert kinds(older.stream_notice(notice(2, 2, 4, takeover_epoch=3)))[-1] is SendLog


def test_fenced_drops_the_log_and_rejoins_once() -> None:
    core = master()
    effects = core.fenced(1, 2)
    assert kinds(effects) == [Record, Note, DisconnectDrone, Rejoin]
    role = effects[0]
    assert isinstance(role, Record) and role.role == ring_pb2.HANDOVER_ROLE_FENCED
    assert core.protocol.fenced and core.rejoining
    assert core.fenced(1, 2) == []  # a rejoin is under way
    assert core.rejoin() == []


def test_a_takeover_older_than_our_mastership_fences_nothing() -> None:
    """--policy nearest seed 712: master 1 (epoch 5) took epoch 7 from a handover message
    handed back to it (``_take_handed_back``); the drone's refusal of its earlier Connect
    then named the takeover of epoch 6, and fenced it (mastership-legal: fenced by an
    epoch not newer than ours). A takeover older than our mastership is moot: it
    connects again in its epoch."""
    core = master()
    core.protocol.epoch = 7  # as the handover message handed back made it
    assert kinds(core.fenced(1, 6)) == [Note, Reconnect]
    assert not core.protocol.fenced and not core.rejoining
    assert Rejoin in kinds(core.fenced(1, 8))


def test_a_takeover_older_than_the_mastership_a_handover_message_gave_fences_nothing() -> None:
    """The same while catching up for it: made master in epoch 5 by a handover message and
    not ACTIVE yet, a controller told of the takeover of epoch 4 (of its mastership of
    epoch 3) connects again in its epoch (``Mastership`` rule 5: the takeover that fences
    us is newer than our mastership)."""
    core = ControllerCore(started(2, [0, 1, 2], 0), True)
    core.protocol.master, core.protocol.epoch = True, 5  # as the handover message made it
    assert core.protocol.state is State.PASSIVE
    assert kinds(core.fenced(1, 4)) == [Note, Reconnect]
    assert not core.protocol.fenced and not core.rejoining
    assert core.protocol.mastership.problems() == []


def test_a_connect_refusal_decides_by_what_the_drone_says() -> None:
    taken = master().connect_refused(DroneRefusal(1, 2, 5, taken_over=True))
    assert Rejoin in kinds(taken)
    replica = ControllerCore(started(1, [0, 1, 2], 0))
    assert kinds(replica.connect_refused(DroneRefusal(0, 1, 5))) == [Note, DisconnectDrone]
    stale = master()
    stale.protocol.on_granted(3)
    assert kinds(stale.connect_refused(DroneRefusal(2, 2, 5))) == [Note, Reconnect]
    # Made master, but the drone moved on meanwhile: the log goes to the master it names.
    moved = master().connect_refused(DroneRefusal(2, 2, 5))
    assert SendLog in kinds(moved)


def test_a_refused_request_is_judged_by_epoch() -> None:
    core = master()
    disagree = core.request_refused(1, DroneRefusal(0, 1, 3), 4, GET, "wrong reqnr")
    fail = disagree[0]
    assert kinds(disagree) == [Fail] and isinstance(fail, Fail) and "refused request 4" in fail.text
    regranted = master().request_refused(1, DroneRefusal(0, 2, 3), 4, GET, "")
    assert kinds(regranted) == [Note, Reconnect]
    handed = master().request_refused(1, DroneRefusal(2, 2, 3), 4, GET, "")
    assert SendLog in kinds(handed)
    fenced = master().request_refused(1, DroneRefusal(2, 2, 3, taken_over=True), 4, GET, "")
    assert Rejoin in kinds(fenced)


def test_a_takeover_reconnects_and_its_grant_counts_as_a_takeover() -> None:
    core = ControllerCore(started(1, [0, 1, 2], 0))
    effects = core.take_over(drone_pb2.TakeOver(old_master=0, epoch=2, after_reqnr=7))
    assert kinds(effects) == [Record, Note, Reconnect]
    record = effects[0]
    assert isinstance(record, Record) and (record.epoch, record.drone_after_reqnr) == (2, 7)
    # The grant does not say takeover: its epoch is the TakeOver's.
    core.granted(drone_pb2.Connected(epoch=2))
    assert core.first_new_call_due and core.protocol.state is State.ACTIVE


def test_retained_replies_above_what_we_hold_are_kept_for_the_program() -> None:
    core = ControllerCore(started(1, [0, 1, 2], 0))
    core.take_over(drone_pb2.TakeOver(old_master=0, epoch=2, after_reqnr=2))
    core.granted(drone_pb2.Connected(epoch=2, retained_through=2, takeover=True))
    digest = request_digest(GET, b"")
    replies = [
        drone_pb2.RetainedReply(reqnr=n, method=GET, request_digest=digest, reply=b"r", epoch=1)
        for n in (1, 2)
    ]
    assert core.retained_batch(replies) == []
    assert sorted(core.retained) == [1, 2] and core.retained_came == 2


def test_a_fresh_self_carries_what_the_rejoin_must_not_forget() -> None:
    core = master()
    core.fenced(1, 3)
    fresh = core.fresh_self()
    assert fresh.protocol.state is State.PASSIVE and not fresh.rejoining
    # Our handover message of a mastership the takeover ended gives the fresh self no
    # role (it would be fenced at every Connect).
    stale = ring_pb2.LogMessage(lognr=1, origin=0, sender=2, handover=True, epoch=2)
    fresh.protocol.start()
    fresh.protocol.on_sync(0)
    fresh.protocol.on_log(stale)
    assert fresh.protocol.state is State.PASSIVE and not fresh.protocol.master


def test_a_gap_is_repaired_when_due_and_again_twice_as_late() -> None:
    """Message 2 missing while 3 is queued: noted at once, repaired at the repair time,
    then again twice as late each time; not while its frames are still coming."""
    core = ControllerCore(started(1, [0, 1, 2], 0))
    core.protocol.on_log(ring_pb2.LogMessage(lognr=1, origin=0, sender=0))
    core.protocol.on_log(ring_pb2.LogMessage(lognr=3, origin=0, sender=0))
    assert core.protocol.missing_lognr == 2
    assert core.gap_due(10.0, 1.0) == [] and core.gap == (2, 10.0, 11.0)
    assert core.gap_due(10.9, 1.0) == []
    assert kinds(core.gap_due(11.0, 1.0)) == [Note, RepairGap]
    assert core.gap == (2, 10.0, 13.0)  # twice as late
    assert core.gap_due(12.0, 1.0, frames_seen_at=11.5) == []  # its frames are coming
    assert core.gap == (2, 12.0, 13.0)
    core.protocol.on_log(ring_pb2.LogMessage(lognr=2, origin=0, sender=0))
    assert core.gap_due(20.0, 1.0) == [] and core.gap is None


def test_the_ring_routes_around_a_successor_down_for_the_detection_time() -> None:
    core = ControllerCore(started(1, [0, 1, 2], 0))
    down = {2: 0.5, 0: 0.0}
    assert core.route_due(down.get, 1.0, drone_connected=False) == []
    down[2] = 1.0
    effects = core.route_due(down.get, 1.0, drone_connected=False)
    assert kinds(effects) == [Note, RouteTo]
    route = effects[1]
    assert isinstance(route, RouteTo) and (route.successor, route.skipped) == (0, [2])
    assert (route.previous, route.natural) == (2, 2)
    assert core.protocol.successor == 0 and core.routed_around == [2]
    down[2] = 0.0  # back: the natural successor again
    back = core.route_due(down.get, 1.0, drone_connected=False)
    assert kinds(back) == [Note, RouteTo] and core.protocol.successor == 2
    # Two controllers: nowhere to route around to.
    two = ControllerCore(started(1, [0, 1], 0))
    assert two.route_due(lambda pid: 99.0, 1.0, drone_connected=False) == []


def timers(effects: list) -> list:
    return [effect for effect in effects if isinstance(effect, Arm | Disarm)]


def test_a_gap_arms_its_repair_when_noted_again_on_a_later_gap_and_disarms_when_filled() -> None:
    """The gap's repair is armed when a step leaves a message missing (``ready``), fired
    once (twice as late after a repair), moved by a later gap, cancelled by the fill."""
    core = ControllerCore(started(1, [0, 1, 2], 0), detection_s=2.0)
    assert core.repair_s == 2.0
    effects = core.log_arrived(ring_pb2.LogMessage(lognr=1, origin=0, sender=0), lambda: True)
    assert timers(core.ready(effects, False, now=9.0)) == []  # nothing missing
    effects = core.log_arrived(ring_pb2.LogMessage(lognr=3, origin=0, sender=0), lambda: True)
    assert timers(core.ready(effects, False, now=10.0)) == [Arm(Timer.GAP, 12.0)]
    assert timers(core.ready([], False, now=11.0)) == []  # the same gap: armed already
    sight = RingSight({}, drone_connected=False)
    fired = core.timer_fired(Timer.GAP, 12.0, sight)
    assert kinds(fired) == [Note, RepairGap]
    assert timers(core.ready(fired, False, now=12.0)) == [Arm(Timer.GAP, 16.0)]  # twice as late
    assert core.timer_fired(Timer.ROUTE, 16.0, sight) == []  # not armed: nothing
    # Message 2 fills it, 5 opens another (4 missing): armed anew from now.
    for lognr in (2, 5):
        message = ring_pb2.LogMessage(lognr=lognr, origin=0, sender=0)
        effects = core.log_arrived(message, lambda: True)
    assert timers(core.ready(effects, False, now=14.5)) == [Arm(Timer.GAP, 16.5)]
    assert core.gap == (4, 14.5, 16.5)
    effects = core.log_arrived(ring_pb2.LogMessage(lognr=4, origin=0, sender=0), lambda: True)
    assert timers(core.ready(effects, False, now=15.0)) == [Disarm(Timer.GAP)]
    assert core.gap is None and core.armed == {}


def test_a_gap_whose_frames_are_arriving_is_armed_again_not_repaired() -> None:
    core = ControllerCore(started(1, [0, 1, 2], 0), detection_s=1.0)
    for lognr in (1, 3):
        core.log_arrived(ring_pb2.LogMessage(lognr=lognr, origin=0, sender=0), lambda: True)
    assert timers(core.ready([], False, now=10.0)) == [Arm(Timer.GAP, 11.0)]
    sight = RingSight({}, drone_connected=False, frames_at={2: 10.8})
    assert core.timer_fired(Timer.GAP, 11.0, sight) == []
    assert timers(core.ready([], False, now=11.0)) == [Arm(Timer.GAP, 12.0)]


def test_a_ring_stream_down_arms_the_route_at_its_detection_time() -> None:
    core = ControllerCore(started(1, [0, 1, 2], 0), detection_s=1.0)
    down = RingSight({2: 4.5}, drone_connected=False)  # the successor's, since 4.5
    assert core.ring_changed(5.0, down) == []
    assert timers(core.ready([], False, now=5.0)) == [Arm(Timer.ROUTE, 5.5)]
    fired = core.timer_fired(Timer.ROUTE, 5.5, down)
    assert kinds(fired) == [Note, RouteTo] and core.protocol.successor == 0
    assert timers(core.ready(fired, False, now=5.5)) == []  # nothing left to wait for
    up = RingSight({}, drone_connected=False)
    back = core.ring_changed(6.0, up)  # its stream is up again: back at once
    assert kinds(back) == [Note, RouteTo] and core.protocol.successor == 2
    # Two streams down at different times: armed for the first to reach it, then the next.
    two = RingSight({2: 7.0, 0: 7.4}, drone_connected=False)
    core.ring_changed(7.0, two)
    assert timers(core.ready([], False, now=7.0)) == [Arm(Timer.ROUTE, 8.0)]
    core.timer_fired(Timer.ROUTE, 8.0, two)
    assert core.protocol.successor == 0
    assert timers(core.ready([], False, now=8.0)) == [Arm(Timer.ROUTE, 8.4)]


def test_a_route_held_back_is_decided_again_when_the_hold_ends() -> None:
    """An ACTIVE master cut off from the drone does not route around its successor
    (``may_route_around``); the drone's stream up again ends the hold, and the route is
    decided at once."""
    core = master()
    core.detection_s = 1.0
    down = RingSight({1: 0.0}, drone_connected=False)
    assert core.ring_changed(2.0, down) == [] and core.route_held
    assert timers(core.ready([], False, now=2.0)) == []  # nothing in time ends it
    assert timers(core.ready([], True, now=3.0)) == [Arm(Timer.ROUTE, 3.0)]
    fired = core.timer_fired(Timer.ROUTE, 3.0, RingSight({1: 0.0}, drone_connected=True))
    assert kinds(fired) == [Note, RouteTo] and core.protocol.successor == 2


def test_a_preparation_arms_its_end_and_a_handover_disarms_it() -> None:
    core = master()
    effects = core.ready(core.prepare(prepare(2, 1, 3.0), now=10.0), True, now=10.0)
    end = 13.0 + PREPARE_GRACE_S
    assert timers(effects) == [Arm(Timer.PREPARATION, end)]
    over = core.timer_fired(Timer.PREPARATION, end, RingSight({}, drone_connected=True))
    assert kinds(over) == [Note] and core.protocol.preparing_for is None
    assert timers(core.ready(over, True, now=end)) == []
    core.ready(core.prepare(prepare(2, 1, 3.0), now=20.0), True, now=20.0)
    handed = core.handover_notice(2, 0, 2)
    assert timers(core.ready(handed, False, now=21.0)) == [Disarm(Timer.PREPARATION)]


def test_a_master_cut_off_with_a_newer_mastership_queued_is_fenced_by_any_step() -> None:
    """A message of a newer mastership came while a stream to the drone was up, and was
    queued; the first step after both streams are down fences the master."""
    core = master()
    taker = ring_pb2.LogMessage(lognr=2, origin=1, sender=1, epoch=3)
    assert Rejoin not in kinds(core.ready(core.log_arrived(taker, lambda: True), True, 1.0))
    assert 2 in core.protocol.log_queue
    fenced = core.ready([], False, now=2.0, drone_reachable=False)
    assert Rejoin in kinds(fenced) and core.rejoining
    assert Rejoin not in kinds(core.ready([], False, now=3.0, drone_reachable=False))


def test_a_sleep_beyond_the_missions_bound_is_logged_as_refused() -> None:
    core = ControllerCore(started(0, [0, 1, 2], 0), max_sleep_s=600.0)
    core.protocol.granted_epoch = core.protocol.epoch
    too_long = api.SleepRequest(seconds=1e12).SerializeToString()
    step, _ = core.answer(CLOCK_SLEEP, too_long)
    assert isinstance(step, Answer) and step.entry.status_code == 3  # INVALID_ARGUMENT
    assert "safety.max_sleep" in step.entry.status_message
    assert core.protocol.reqnr == 1  # logged: every replica's program sees the refusal
    fine = api.SleepRequest(seconds=1.0).SerializeToString()
    assert isinstance(core.answer(CLOCK_SLEEP, fine)[0], AskClock)


class _Held:
    """A history of whole log messages, as ``HeldLog`` reads it."""

    def __init__(self, *lognrs: int) -> None:
        self.messages = {n: ring_pb2.LogMessage(lognr=n, origin=0, epoch=1) for n in lognrs}

    def above(self, lognr: int):  # type: ignore[no-untyped-def]
        return iter(sorted(n for n in self.messages if n > lognr))

    def get(self, lognr: int) -> ring_pb2.LogMessage:
        return self.messages[lognr]


def test_ready_persists_before_sending_and_holds_a_copy_back_while_cut_off() -> None:
    core = master()
    normal = SendLog(1, ring_pb2.LogMessage(lognr=5, origin=0, epoch=1))
    handover = SendLog(2, ring_pb2.LogMessage(lognr=6, origin=0, epoch=1, handover=True))
    copy = SendLog(2, ring_pb2.LogMessage(lognr=5, origin=0, epoch=1), copy=True)
    ready = core.ready([normal, handover, copy], drone_connected=False, now=0.0)
    # A normal message enters the history first; a handover message when it comes back
    # round; a copy for a prepared target not at all while the drone's stream is down.
    # The master's first step says its word (``SayWord``).
    assert kinds(ready) == [Persist, SendLog, SendLog, KeepMastership, SayWord]
    assert ready[0] == Persist(normal.message) and ready[1] is normal and ready[2] is handover
    assert kinds(core.ready([copy], drone_connected=True, now=0.0)) == [SendLog, KeepMastership]
    assert core.sent_straight == {2: 5}


def test_a_replayed_answer_is_carried_out_as_it_is_and_moves_no_deadline() -> None:
    """A step that only answers a replayed call skips the deadlines' comparison: a full
    step right after it arms and disarms nothing. The log's last entry ends REPLAY and
    takes the full way."""
    core = ControllerCore(started(1, [0, 1, 2], 0), detection_s=1.0)
    digest = request_digest(GET, b"")
    entries = [ring_pb2.LogEntry(reqnr=k, method=GET, request_digest=digest) for k in (1, 2, 3)]
    logged = ring_pb2.LogMessage(lognr=1, origin=0, sender=0, entries=entries)
    core.ready(core.log_arrived(logged, lambda: True), False, now=1.0)
    core.log_arrived(ring_pb2.LogMessage(lognr=3, origin=0, sender=0), lambda: True)  # 2 lacks
    core.ring_changed(1.0, RingSight({2: 0.5}, drone_connected=False))
    armed = timers(core.ready([], False, now=1.0))
    assert armed == [Arm(Timer.GAP, 2.0), Arm(Timer.ROUTE, 1.5)]
    assert core.protocol.state is State.REPLAY
    for now in (1.1, 1.2):
        step, effects = core.answer(GET, b"")
        assert isinstance(step, Answer) and effects == [Seen(step.entry, replayed=True)]
        assert core.ready(effects, False, now) == effects  # nothing persisted, kept or armed
        assert timers(core.ready([], False, now)) == []  # nothing the step skipped was due
    step, effects = core.answer(GET, b"")  # the last entry: REPLAY ends
    assert isinstance(step, Answer) and effects[0] == Seen(step.entry)
    assert core.protocol.state is not State.REPLAY
    assert KeepMastership in kinds(core.ready(effects, False, now=1.3))


def test_ready_rejoins_once_on_a_diverged_log() -> None:
    core = master()
    diverged = Diverged(4, 1, 3)
    first = [Diverged, Rejoin, KeepMastership, SayWord]  # the master's first step: its word
    assert kinds(core.ready([diverged], True, 0.0)) == first
    assert kinds(core.ready([diverged], True, 0.0)) == [Diverged, KeepMastership]


def test_the_catch_up_sends_each_message_once_and_nothing_to_the_successor() -> None:
    core = master()
    held = _Held(1, 2, 3)
    assert core.catch_up(1, held) is None  # the successor's ring stream gives it all
    assert [m.lognr for m in core.catch_up(2, held) or []] == [1, 2, 3]
    held.messages[4] = ring_pb2.LogMessage(lognr=4, origin=0, epoch=1)
    assert [m.lognr for m in core.catch_up(2, held) or []] == [4]
    assert core.catch_up(2, held) == []


def test_the_catch_up_leaves_out_the_messages_of_earlier_masterships() -> None:
    """A master in epoch 2 holds messages of epoch 1 it passed on as a replica: they
    went on along the ring before its own, and a signed ring's ``acked_lognr`` counts
    only its own. Sent straight too, each crossed the target's link a second time
    ahead of the master's own: a 1 MB cut-through handover over 3 hops took 1.39 s
    against 0.76 s (``baton bench worst-case --quick``: 2.1 MB more into the target)."""
    core = master()
    core.protocol.epoch = 2
    held = _Held(1, 2, 3)
    held.messages[3].epoch = 2
    assert [m.lognr for m in core.catch_up(2, held) or []] == [3]


def test_a_rejoin_keeps_what_went_round_and_the_handover_messages_nowhere_else() -> None:
    core = master()
    assert core.kept_on_rejoin(_Held(1, 2)) == []  # a master that was not fenced keeps nothing


def test_a_route_retires_a_successor_it_no_longer_needs() -> None:
    assert RouteTo(1, [], previous=2, natural=1).retired == 2
    assert RouteTo(2, [1], previous=1, natural=1).retired is None  # the natural one
    assert RouteTo(0, [1, 2], previous=2, natural=1).retired is None  # skipped now


def test_a_drone_reply_says_the_drone_took_the_watermark_its_call_carried() -> None:
    """The drone raises its watermark to what a call of its master carries before it
    answers it: a reply the drone signed for it (``drone_epoch``) tells the master the
    drone took at least the watermark it had when it asked (every attempt carries that
    or more); a give-up after the retries, which the drone may never have seen, does not."""
    core = master()
    p = core.protocol
    p.watermark_reqnr = 4  # as the ring's proofs moved it
    step, _ = core.answer(GET, b"")
    assert isinstance(step, AskDrone) and step.reqnr == 1 and core.asked_with == (1, 4)
    p.watermark_reqnr = 6  # a retry carries more
    gave_up = ring_pb2.LogEntry(reqnr=1, method=GET, status_code=14)
    core.logged(1, gave_up)
    assert p.told_watermark == 0
    step, _ = core.answer(GET, b"")
    reply = ring_pb2.LogEntry(reqnr=2, method=GET, reply=b"at", drone_epoch=1)
    core.logged(2, reply)
    assert p.told_watermark == 6


def test_a_takeover_that_gives_the_role_back_keeps_the_log_no_takeover_replaced() -> None:
    """--lose-master --prepared seed 198: master 1, ACTIVE in epoch 5, never heard of the
    forced handover to the dead controller 0 (epoch 6), which waited for its handover
    message; the drone took the role back to 1 (epoch 7). 1 took the grant for one of a
    mastership a takeover replaced and rejoined with nothing, dropping the only copy of
    requests 1-14, and waited for ever. The takeover two epochs on, to us, replaced
    nothing of ours: we stay ACTIVE with our log. One later than that may follow another
    master's takeover that framed our requests anew: fenced, as before."""
    core = master()
    core.protocol.on_reply(ring_pb2.LogEntry(reqnr=1, method=GET, reply=b"r"))
    effects = core.granted(drone_pb2.Connected(epoch=3, takeover=True, takeover_epoch=3))
    assert Rejoin not in kinds(effects) and core.protocol.state is State.ACTIVE
    assert core.protocol.epoch == 3 and core.protocol.held_reqnr == 1
    later = master()
    assert Rejoin in kinds(
        later.granted(drone_pb2.Connected(epoch=4, takeover=True, takeover_epoch=4))
    )
    handed_back = master()  # a handover grant after another's takeover: replaced
    assert Rejoin in kinds(handed_back.granted(drone_pb2.Connected(epoch=4, takeover_epoch=3)))


def test_the_connect_names_the_mastership_whose_log_we_hold_and_what_it_holds() -> None:
    """ConnectRequest as both drivers send it (``ControllerCore.connect_request``): a
    replica names no mastership; the master its epoch and the request its log holds."""
    replica = ControllerCore(started(1, [0, 1, 2], 0))
    assert replica.connect_request() == drone_pb2.ConnectRequest(controller_id=1)
    core = master()
    entry = ring_pb2.LogEntry(reqnr=1, method=GET, request_digest=request_digest(GET, b""))
    core.protocol.on_reply(entry)
    request = core.connect_request()
    assert (request.controller_id, request.mastership_epoch) == (0, 1)
    assert (request.holds_reqnr, request.given_up_epoch) == (1, 0)


def test_a_master_word_heard_is_said_on_though_it_drops_nothing_here() -> None:
    """A replica holding no stale message hears of a newer ACTIVE master: the word goes
    on to its successor all the same, for a controller further on whose stale queued
    message it drops (else that one repairs a gap every few seconds for ever)."""
    replica = ControllerCore(started(1, [0, 1, 2], 0), True)
    replica.ready([], False, 0.0)
    word = SyncWord(holds=4, holds_epoch=10, master_epoch=12, master_lognr=4)
    said = replica.ready(replica.sync_arrived(0, word), False, 1.0)
    assert SayWord in kinds(said)
    assert replica.protocol.master_word == (12, 4)
    # The same word again, or an older one: nothing new to say.
    again = replica.ready(replica.sync_arrived(0, word), False, 2.0)
    older = SyncWord(holds=4, holds_epoch=10, master_epoch=11, master_lognr=3)
    assert SayWord not in kinds(again + replica.ready(replica.sync_arrived(0, older), False, 3.0))


def test_a_master_gone_active_says_its_word_though_it_logs_nothing() -> None:
    core = ControllerCore(started(0, [0, 1, 2], 0), True)
    assert core.protocol.state is State.ACTIVE
    assert SayWord in kinds(core.ready([], True, 0.0))
    assert SayWord not in kinds(core.ready([], True, 1.0))


def test_an_adoption_no_drone_call_carried_is_carried_by_our_next_mastership() -> None:
    """A taker answered requests 1-2 from the retained replies; the call that would have
    told the drone so (``adopted_from_reqnr``) was overtaken by a handover. The drone
    gives the role back to us by takeover in epoch 4: our calls there still say it (the
    drone counts those replies as brought in epoch 4, newer than a lost master's
    give-up of one of them the ring may hold), until the drone answered one."""
    core = ControllerCore(started(1, [0, 1, 2], 0))
    core.take_over(drone_pb2.TakeOver(old_master=0, epoch=2, after_reqnr=2))
    core.granted(drone_pb2.Connected(epoch=2, retained_through=2, takeover=True))
    digest = request_digest(GET, b"")
    core.retained_batch(
        [
            drone_pb2.RetainedReply(reqnr=n, method=GET, request_digest=digest, reply=b"r", epoch=1)
            for n in (1, 2)
        ]
    )
    for _ in (1, 2):
        assert isinstance(core.answer(GET, b"")[0], Answer)
    assert isinstance(core.answer(GET, b"")[0], AskDrone)
    assert core.carried(None).adopted_from_reqnr == 1
    # No answer to request 3 in epoch 2: the drone took the role away, and back.
    core.take_over(drone_pb2.TakeOver(old_master=0, epoch=4, after_reqnr=2))
    core.granted(drone_pb2.Connected(epoch=4, retained_through=2, takeover=True))
    assert core.protocol.epoch == 4
    assert core.carried(None).adopted_from_reqnr == 1
    answered = ring_pb2.LogEntry(reqnr=3, method=GET, request_digest=digest, drone_epoch=4)
    assert core.logged(3, answered)[0] is not None
    assert core.carried(None).adopted_from_reqnr == 0


def test_a_takers_drone_calls_say_the_log_number_its_own_messages_follow() -> None:
    """A taker's messages follow what it held when it went ACTIVE; its drone calls say
    so (``framed_after_lognr``), for the drone to refuse a later taker that holds
    another framing of those numbers. A master granted otherwise says nothing."""
    cooperative = master()
    assert not cooperative.carried(None).HasField("framed_after_lognr")
    taker = ControllerCore(started(1, [0, 1, 2], 0))
    taker.protocol.on_log(
        ring_pb2.LogMessage(
            lognr=1, origin=0, sender=0, epoch=1, after_reqnr=0, entries=[_entry(1), _entry(2)]
        )
    )
    for _ in (1, 2):  # the program replays the log
        assert isinstance(taker.answer(GET, b"")[0], Answer)
    assert taker.protocol.lognr == 1
    taker.take_over(drone_pb2.TakeOver(old_master=0, epoch=2, after_reqnr=2))
    taker.granted(drone_pb2.Connected(epoch=2, takeover=True))
    assert taker.protocol.state is State.ACTIVE
    carried = taker.carried(None)
    assert (carried.framed_after_lognr, carried.framed_after_epoch) == (1, 1)


def test_a_grant_that_says_our_framing_was_replaced_makes_us_rejoin_refusing_it() -> None:
    """--policy predictive 19072: taker 1 held messages 13-15 of epoch 3, which the
    takeover of epoch 4 had numbered otherwise from 13 on; built on, its messages could
    not follow the ring's. The drone's grant says so: we rejoin before acting, and our
    fresh self refuses those numbers in every epoch older than the one that replaced
    them, while the ring's (of that epoch or newer) are taken."""
    taker = ControllerCore(started(1, [0, 1, 2], 0))
    taker.take_over(drone_pb2.TakeOver(old_master=0, epoch=8, after_reqnr=21))
    effects = taker.granted(
        drone_pb2.Connected(epoch=8, takeover=True, replaced_from_lognr=13, replaced_by_epoch=4)
    )
    assert kinds(effects) == [Note, Rejoin]
    assert taker.protocol.state is not State.ACTIVE
    fresh = taker.fresh_self().protocol
    fresh.start()
    ours = ring_pb2.LogMessage(lognr=13, origin=0, sender=0, epoch=3, after_reqnr=16)
    assert [type(e).__name__ for e in fresh.on_log(ours)] == ["Fenced"]
    rings = ring_pb2.LogMessage(lognr=13, origin=0, sender=0, epoch=4, after_reqnr=16)
    assert [type(e).__name__ for e in fresh.on_log(rings)] == ["SendLog"]


def _entry(reqnr: int) -> ring_pb2.LogEntry:
    return ring_pb2.LogEntry(
        reqnr=reqnr, method=GET, reply=b"r", request_digest=request_digest(GET, b"")
    )
