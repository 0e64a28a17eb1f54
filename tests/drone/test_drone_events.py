"""The drone core's events that move the master and book requests, and the effects they
return in their documented order (drone/effects.py); a Connect stream's events
(drone/connects.py). Pure: no sockets, no clock, every time an argument."""

from __future__ import annotations

from typing import TypeVar

import grpc
import pytest

from baton.authenticity import signed_reply, signed_retained
from baton.digest import request_digest
from baton.drone.connects import ConnectStream
from baton.drone.core import RESTART_GRACE_S, DroneCore, Kept
from baton.drone.dedupe import CachedReply
from baton.drone.effects import (
    Abandon,
    Book,
    DroneEffect,
    Note,
    Preparing,
    SaveCounters,
    Switched,
    TellTakeOver,
    pins_policy,
)
from baton.drone.invocations import answered_again
from baton.drone.policy import HANDOVER, MOVED, PREPARE, SWITCH, Decision
from baton.drone.safety import ModeSeen, SafetyParams
from baton.drone.sequencer import ScriptedHandover, Sequencer
from baton.drone.sight import DroneSight
from baton.drone.store import Intent
from baton.rpc.errors import StatusError
from baton.sim.lying import sim_keys
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2

E = TypeVar("E")
GET = "/baton.v1.Mobility/GetPosition"
RPC = drone_pb2.HANDOVER_TRIGGER_RPC
POLICY = drone_pb2.HANDOVER_TRIGGER_POLICY


def core(
    takeover_after_s: float = 1.0,
    script: dict[int, ScriptedHandover] | None = None,
    safety: SafetyParams | None = None,
) -> DroneCore:
    """Ring 0 -> 1 -> 2, master 0; a preparation waits 4 s."""
    seq = Sequencer([0, 1, 2], initial_master=0, script=script, prepare_timeout_s=4.0)
    return DroneCore(seq, takeover_after_s, safety)


def serve(
    drone: DroneCore, reqnr: int, cid: int = 0, epoch: int = 1, now: float = 0.0
) -> list[DroneEffect]:
    """Request ``reqnr`` of ``cid`` admitted and served with an empty reply."""
    request = drone_pb2.InvokeRequest(controller_id=cid, epoch=epoch, reqnr=reqnr, method=GET)
    digest = request_digest(GET, b"")
    admitted = drone.admit(request, digest, now)
    assert admitted.cached is None
    return drone.served(cid, reqnr, GET, digest, b"", now, now)


def the(kind: type[E], effect: DroneEffect) -> E:
    """``effect``, which must be a ``kind``."""
    assert isinstance(effect, kind)
    return effect


def kinds(effects: list[DroneEffect]) -> list[type]:
    return [type(effect) for effect in effects]


def connected_master(drone: DroneCore) -> None:
    """The master has connected and served once: it can hand over cooperatively."""
    serve(drone, 1)


def test_a_cooperative_handover_saves_then_wakes_the_old_master() -> None:
    drone = core()
    connected_master(drone)
    effects = drone.hand_over(1, RPC, 5.0)
    assert kinds(effects) == [SaveCounters, Switched]
    record = the(Switched, effects[1]).record
    assert (record.old_master, record.new_master, record.epoch) == (0, 1, 2)
    assert record.kind == drone_pb2.HANDOVER_KIND_COOPERATIVE
    assert pins_policy(record)  # an operator chose it


def test_a_handover_from_a_master_that_could_not_send_its_log_is_a_takeover() -> None:
    """The initial master, never connected and with nothing served, cannot send its log:
    the switch is a takeover, and the new master is told on its standby stream."""
    drone = core()
    effects = drone.hand_over(2, RPC, 5.0)
    assert kinds(effects) == [SaveCounters, Switched, TellTakeOver]
    told = the(TellTakeOver, effects[2])
    assert told.record.new_master == 2 and told.take_over.epoch == 2
    assert told.take_over.old_master == 0 and told.lost_at == 0.0


def test_a_handover_call_refuses_an_unknown_controller_and_the_master_itself() -> None:
    drone = core()
    with pytest.raises(StatusError) as unknown:
        drone.handover_call(7, prepared=False, takeover=False, master_connected=True, now=1.0)
    assert unknown.value.code is grpc.StatusCode.INVALID_ARGUMENT
    with pytest.raises(StatusError) as itself:
        drone.handover_call(0, prepared=False, takeover=False, master_connected=True, now=1.0)
    assert itself.value.code is grpc.StatusCode.FAILED_PRECONDITION
    assert not drone.seq.handovers


def test_a_prepared_handover_call_prepares_only_for_a_connected_master() -> None:
    drone = core()
    connected_master(drone)
    at_once = core()
    connected_master(at_once)
    # Without its Connect stream the master cannot hear the PrepareHandover: at once.
    assert kinds(at_once.handover_call(1, True, False, False, 2.0)) == [SaveCounters, Switched]
    effects = drone.handover_call(1, True, False, True, 2.0)
    assert kinds(effects) == [Preparing]
    assert the(Preparing, effects[0]).notice.target == 1 and drone.seq.preparing is not None
    # The master's Connect stream carries it once, then nothing until the switch.
    stream = ConnectStream(0)
    assert stream.woken(drone, operator_words=False) == [the(Preparing, effects[0]).notice]
    assert stream.woken(drone, operator_words=False) == []


def test_a_preparation_is_forced_at_its_deadline_by_the_master_watch() -> None:
    drone = core(takeover_after_s=0.0)
    connected_master(drone)
    (preparing,) = drone.handover_call(1, True, False, True, 2.0)
    assert isinstance(preparing, Preparing)
    assert drone.master_watch(5.9, {0, 1, 2}, {0}, None) == []
    effects = drone.master_watch(6.0, {0, 1, 2}, {0}, None)
    assert kinds(effects) == [SaveCounters, Switched]
    record = the(Switched, effects[1]).record
    assert record.prepare_timed_out and record.new_master == 1
    assert drone.prepared_outcome(1, 2.0) is record


def test_a_preparation_replaced_by_another_switch_is_aborted_for_its_caller() -> None:
    drone = core()
    connected_master(drone)
    drone.handover_call(1, True, False, True, 2.0)
    started = drone.seq.preparing
    assert started is not None
    drone.hand_over(2, RPC, 3.0)  # another operator's switch, at once
    with pytest.raises(StatusError) as replaced:
        drone.prepared_outcome(1, started.started_at)
    assert replaced.value.code is grpc.StatusCode.ABORTED
    assert "to controller 1 being prepared was replaced" in replaced.value.message


def test_the_master_watch_takes_a_lost_master_over_and_tells_the_taker() -> None:
    drone = core(takeover_after_s=1.0)
    connected_master(drone)
    assert drone.master_watch(0.5, {0, 1, 2}, {0}, None) == []
    effects = drone.master_watch(20.0, {1, 2}, set(), None)
    assert kinds(effects) == [SaveCounters, Switched, TellTakeOver]
    told = the(TellTakeOver, effects[2])
    assert told.record.trigger == drone_pb2.HANDOVER_TRIGGER_LOST
    assert told.record.new_master == 1 and told.lost_at > 0.0


def test_the_master_s_word_moves_the_master_once_the_target_caught_up() -> None:
    drone = core()
    connected_master(drone)
    drone.handover_call(1, True, False, True, 2.0)
    behind = drone_pb2.PreparationProgress(target=1, lacks_bytes=10**9, acked=3, after_reqnr=1)
    assert drone.preparation_word(0, 1, behind, 2.5) == []
    caught_up = drone_pb2.PreparationProgress(target=1, lacks_bytes=0, acked=3, after_reqnr=1)
    effects = drone.preparation_word(0, 1, caught_up, 3.0)
    assert kinds(effects) == [SaveCounters, Switched]
    assert the(Switched, effects[1]).record.kind == drone_pb2.HANDOVER_KIND_PREPARED


def test_a_served_request_is_booked_before_the_script_s_handover() -> None:
    drone = core(script={1: ScriptedHandover(1, 1, 1), 2: ScriptedHandover(2, 1, 2)})
    effects = serve(drone, 1)
    assert kinds(effects) == [Book, Switched]
    assert the(Book, effects[0]).served.audit.reqnr == 1
    # The second line names the master itself: booked, skipped, said in the log.
    skipped = serve(drone, 2, cid=1, epoch=2, now=1.0)
    assert kinds(skipped) == [Book, Note]
    assert the(Note, skipped[1]).fields["script_line"] == 2


def test_a_failure_that_reached_nothing_is_not_booked() -> None:
    drone = core()
    unavailable = StatusError(grpc.StatusCode.UNAVAILABLE, "the vehicle is not connected")
    assert kinds(drone.failed(0, 1, GET, b"", 0.0, 0.0, unavailable)) == [Abandon]
    refused = StatusError(grpc.StatusCode.FAILED_PRECONDITION, "in failsafe")
    booked = drone.failed(0, 1, GET, b"", 0.0, 0.0, refused)
    assert kinds(booked) == [Book]
    assert the(Book, booked[0]).served.cached.error is not None


def test_a_fresh_self_of_the_master_is_granted_a_new_epoch_once() -> None:
    """Master 1 in epoch 2 restarted with nothing and says its earlier self gave the
    epoch's log up: a takeover of its earlier self grants it epoch 3."""
    drone = core()
    connected_master(drone)
    drone.hand_over(1, RPC, 2.0)
    assert drone.seq.fresh_self_due(1, 0, 2)
    effects = drone.fresh_self_connect(1, 2, 5.0)
    assert kinds(effects) == [SaveCounters, Switched, Note]
    assert drone.seq.epoch == 3 and the(Switched, effects[1]).record.new_master == 1
    assert drone.fresh_self_connect(1, 2, 6.0) == []  # a second Connect: the epoch moved on


def test_the_policy_switches_or_prepares_only_for_the_master_it_decided_for() -> None:
    drone = core()
    connected_master(drone)
    decision = Decision(HANDOVER, "out of range", target=1)
    assert drone.policy_handover(decision, 2, True, 1.0) == (MOVED, [])
    step, effects = drone.policy_handover(decision, 0, True, 1.0)
    assert step == PREPARE and kinds(effects) == [Preparing]
    assert drone.seq.preparing is not None and drone.seq.preparing.reason == "out of range"
    step, effects = core().policy_handover(decision, 0, False, 1.0)
    assert (step, kinds(effects)) == (SWITCH, [SaveCounters, Switched, TellTakeOver])
    assert not pins_policy(the(Switched, effects[1]).record)


def test_a_connect_carries_the_grant_then_the_operator_s_word_when_it_changes() -> None:
    drone = core()
    stream = ConnectStream(0)
    grant, batches = stream.opened(drone, drone_pb2.ConnectRequest(controller_id=0))
    assert grant is not None and grant.master == 0 and batches == []
    assert stream.woken(drone) == []
    drone.operator.pause(1.0, 0, note="a person on the field")
    (word,) = stream.woken(drone)
    assert isinstance(word, drone_pb2.OperatorWord) and word.paused
    assert stream.woken(drone) == []  # said once


def test_an_old_master_s_connect_carries_only_its_notice() -> None:
    drone = core()
    connected_master(drone)
    drone.hand_over(1, RPC, 2.0)
    stream = ConnectStream(0)
    assert stream.opened(drone, drone_pb2.ConnectRequest(controller_id=0)) == (None, [])
    (notice,) = stream.woken(drone)
    assert isinstance(notice, drone_pb2.HandoverNotice) and notice.new_master == 1
    drone.delivered(0, notice)
    assert stream.woken(drone) == []


def test_a_look_at_the_vehicle_puts_the_battery_before_the_fence_and_the_lost_link() -> None:
    safety = SafetyParams(lost_link_s=10.0, lost_link_action="hold", battery_reserve_pct=20.0)
    drone = core(safety=safety)
    seen = ModeSeen("HOLD", True, True)
    here = api.Position(latitude_deg=1.0, longitude_deg=1.0)
    assert drone.failsafe_check(0.0, True, 50.0, here, seen, {0}, None) is None
    lost = drone.failsafe_check(10.0, True, 50.0, here, seen, set(), None)
    assert lost is not None and lost.cause == "lost_link"
    drone.enter_failsafe(lost)
    assert drone.failsafe_check(11.0, True, 50.0, None, seen, set(), None) is None
    battery = drone.failsafe_check(12.0, True, 10.0, None, seen, set(), None)
    assert battery is not None and battery.cause == "battery"


def kept(executing: Intent | None = None) -> Kept:
    """A store that kept 3 requests served by master 0, a Goto commanded last."""
    return Kept(0, [], (3, 3, 0, 0), [], [], [], 3, ("fly",), None, executing)


def test_a_restart_abandons_a_read_it_cut_off_and_books_a_command() -> None:
    read = core()
    effects = read.restarted(100.0, kept(Intent(4, GET, b"", 0, 99.0)))
    assert kinds(effects) == [Abandon, Note]
    assert read.seq.last_reqnr == 3
    assert read.vehicle_command is not None
    assert read.vehicle_command.at == 100.0 + RESTART_GRACE_S  # read after the grace
    goto = "/baton.v1.Mobility/Goto"
    command = core()
    effects = command.restarted(100.0, kept(Intent(4, goto, b"", 0, 99.0)))
    assert kinds(effects) == [Note, Book]
    cached = the(Book, effects[1]).served.cached
    assert cached.error is not None and cached.error.code is grpc.StatusCode.UNKNOWN
    assert command.seq.last_reqnr == 4
    assert core().restarted(100.0, kept()) == []


@pytest.mark.parametrize(
    "method",
    [
        "/baton.v1.Mobility/Goto",
        "/baton.v1.Camera/TakePicture",
        "/baton.v1.Gimbal/SetRoiLocation",
        "/baton.v1.Gimbal/ClearRoi",
    ],
)
def test_a_call_that_needs_the_vehicle_is_unavailable_while_it_is_not_connected(
    method: str,
) -> None:
    """A Mobility or Gimbal call reaches the vehicle (the gimbal is commanded over the
    vehicle's link); a picture is taken where it is and says where, so with the vehicle
    not connected none is taken either. Nothing executed: the number
    stays unused (the master sends it again). Setting the resolution needs no vehicle."""
    drone = core()
    refused = drone.unreachable(method, False, "at udp://:14540 (no heartbeat)")
    assert refused is not None and refused.code is grpc.StatusCode.UNAVAILABLE
    assert "not connected" in refused.message and not drone.books(refused)
    assert drone.unreachable(method, True, "") is None
    assert drone.unreachable("/baton.v1.Camera/SetResolution", False, "") is None


def test_a_connect_stream_signs_the_retained_replies_the_drone_made() -> None:
    """The retained replies leave in batches signed with the drone's key
    (``ConnectStream.opened``, for the service and the simulation alike); unsigned
    without one."""
    drone = core()
    digest = request_digest(GET, b"")
    for reqnr in (1, 2):
        drone.seq.admit(0, 1, reqnr, GET, digest)
        drone.seq.served(0, reqnr, GET, digest, b"x" * 40, float(reqnr), float(reqnr))
    signer = sim_keys(0, [0, 1, 2]).drone
    _, signed = ConnectStream(0, signer).opened(
        drone, drone_pb2.ConnectRequest(controller_id=0), batch_bytes=64
    )
    assert [[reply.reqnr for reply in batch] for batch in signed] == [[1], [2]]
    kept = drone.seq.cache.get(1)
    assert kept is not None
    assert signed[0][0] == signed_retained(signer, kept.to_proto())
    assert signed[0][0].signature
    _, unsigned = ConnectStream(0).opened(
        drone, drone_pb2.ConnectRequest(controller_id=0), batch_bytes=64
    )
    assert not unsigned[0][0].signature


def test_a_duplicate_is_answered_with_the_cached_reply_or_its_failure_again() -> None:
    """``invocations.answered_again``: the reply as served, marked a duplicate and signed;
    a cached failure raised again, marked a duplicate's."""
    signer = sim_keys(0, [0, 1, 2]).drone
    digest = request_digest(GET, b"")
    reply = answered_again(signer, 3, CachedReply(3, GET, digest, b"here", epoch=2))
    assert (reply.reqnr, reply.payload, reply.epoch, reply.duplicate) == (3, b"here", 2, True)
    assert reply == signed_reply(signer, 3, 2, GET, digest, b"here", duplicate=True)
    failure = StatusError(grpc.StatusCode.ABORTED, "the vehicle refused")
    with pytest.raises(StatusError) as raised:
        answered_again(signer, 3, CachedReply(3, GET, digest, b"", failure, epoch=2))
    assert raised.value.code is grpc.StatusCode.ABORTED
    assert ("baton-duplicate", "true") in raised.value.metadata


def test_the_watches_see_the_master_serve_only_while_it_holds_its_connect_stream() -> None:
    """``DroneSight``: the master watch is given the master as serving exactly when the
    sight says it holds its Connect stream; the failsafe watch the same holders."""
    drone = core()
    drone.seq.switch(1, RPC, 10.0)
    connected = DroneSight({0, 1, 2}, master_connected=True)
    assert connected.connected(drone) == {1}
    assert connected.takeover_due(drone, 12.0) is None  # served at 12
    unconnected = DroneSight({0, 1, 2}, master_connected=False)
    assert unconnected.connected(drone) == set()
    assert unconnected.takeover_due(drone, 15.9) is None
    due = unconnected.takeover_due(drone, 16.0)
    assert due is not None and (due.new_master, due.lost) == (2, 1)
    assert kinds(unconnected.master_watch(drone, 16.0))[:2] == [SaveCounters, Switched]
