"""The receiving end of one LogRing stream, fed frames in a chosen order
(``controller/receiver_core.py``): what it refuses, delivers, acknowledges and passes on."""

from __future__ import annotations

import grpc
import pytest
from google.protobuf.message import DecodeError

from baton.controller.link_core import SyncWord
from baton.controller.receiver_core import (
    AbortRelay,
    Ack,
    Action,
    Arriving,
    Deliver,
    Hello,
    ReceiverCore,
    Refuse,
    RelayFrame,
    SettleRelay,
    StartRelay,
    Synced,
    WaitForRoom,
)
from baton.controller.ring import frames, head_of
from baton.v1 import ring_pb2

FRAME = 100  # bytes of a frame in these tests: a message of a few hundred is a few frames


def message(lognr: int, size: int = 250) -> ring_pb2.LogMessage:
    return ring_pb2.LogMessage(
        lognr=lognr,
        origin=0,
        epoch=2,
        entries=[
            ring_pb2.LogEntry(reqnr=lognr, method="/baton.v1.Camera/TakePicture", reply=b"p" * size)
        ],
    )


def parts(lognr: int, from_id: int = 0, size: int = 250) -> list[ring_pb2.LogFrame]:
    out = frames(message(lognr, size), from_id, FRAME)
    assert len(out) == 3  # a first, a middle and a last frame
    return out


def feed(core: ReceiverCore, frame: ring_pb2.LogFrame, started: bool = True) -> list[Action]:
    """The frame's actions as a driver applies them: a StartRelay answered ``started``."""
    actions = core.frame(frame)
    if actions and isinstance(actions[-1], StartRelay):
        actions = actions + core.relay_started(started)
    return actions


class Held:
    """A ``held`` query whose answers are given in turn (then False), counting the asks."""

    def __init__(self, *answers: bool) -> None:
        self.answers = list(answers)
        self.asked: list[int] = []

    def __call__(self, head: ring_pb2.LogMessage) -> bool:
        self.asked.append(head.lognr)
        return self.answers.pop(0) if self.answers else False


# -- the hello, sync frames ---------------------------------------------------------


def test_the_hello_says_the_number_handled_and_its_epoch_none_when_nothing_is_held() -> None:
    core = ReceiverCore(1)
    asked: list[int] = []

    def epoch_of(lognr: int) -> int:
        asked.append(lognr)
        return 4

    assert core.opened(7, epoch_of) == Hello(7, 4)
    assert core.opened(0, epoch_of) == Hello(0, 0)
    assert core.opened(7) == Hello(7, 0)
    assert asked == [7]


def test_a_sync_frame_says_what_its_sender_holds_and_is_no_part_of_a_message() -> None:
    core = ReceiverCore(1, sender=0)
    first, middle, last = parts(3)
    feed(core, first)
    sync = ring_pb2.LogFrame(
        sync=True, from_id=0, holds_lognr=5, holds_epoch=2, master_epoch=3, master_lognr=4
    )
    assert core.frame(sync) == [Synced(0, SyncWord(5, 2, 3, 4))]
    assert feed(core, middle) == [Arriving(3)]
    assert feed(core, last) == [Arriving(3), Deliver(message(3), 0), Ack(3)]


# -- refusals -----------------------------------------------------------------------


def test_a_frame_from_another_controller_than_the_certificates_is_refused() -> None:
    core = ReceiverCore(1, sender=0)
    (frame,) = frames(message(1, 10), from_id=2)
    assert core.frame(frame) == [
        Refuse(
            grpc.StatusCode.PERMISSION_DENIED,
            "LogRing: controller 0's certificate sent a frame from_id 2; a controller sends "
            "its own frames only",
        )
    ]
    sync = ring_pb2.LogFrame(sync=True, from_id=2)
    assert isinstance(core.frame(sync)[0], Refuse)  # a sync frame too
    # Without a certificate's word (an insecure ring), any sender's frames are taken.
    assert ReceiverCore(1).frame(frame)[-1] == Ack(1)


def test_what_is_not_a_log_frame_is_refused() -> None:
    assert ReceiverCore(1).undecodable(DecodeError("Error parsing message")) == [
        Refuse(
            grpc.StatusCode.INVALID_ARGUMENT,
            "LogRing: a frame that is not a LogFrame (Error parsing message); nothing of it "
            "was taken",
        )
    ]


def test_a_frame_that_does_not_follow_is_refused() -> None:
    core = ReceiverCore(1)
    first, _, last = parts(4)
    feed(core, first)
    assert feed(core, last) == [
        Refuse(
            grpc.StatusCode.INVALID_ARGUMENT,
            "frame of log message 4 at offset 200 does not follow message 4 at offset 100",
        )
    ]


def test_a_message_claiming_more_than_the_limit_is_refused_and_not_relayed() -> None:
    core = ReceiverCore(1, max_bytes=1000, relays=True)
    claim = ring_pb2.LogFrame(lognr=3, total_bytes=2000, offset=0, data=b"x", from_id=0)
    claim.head.lognr = 3
    assert core.frame(claim) == [
        Refuse(
            grpc.StatusCode.INVALID_ARGUMENT,
            "log message 3 claims 2000 bytes, above max_log_message (1000 bytes); raise it in "
            "the testbed file if missions log larger entries",
        )
    ]


def test_a_message_that_overruns_its_size_or_does_not_parse_is_refused() -> None:
    overrun = ring_pb2.LogFrame(lognr=5, total_bytes=2, offset=0, data=b"xyz", from_id=0)
    assert ReceiverCore(1).frame(overrun) == [
        Refuse(grpc.StatusCode.INVALID_ARGUMENT, "log message 5 overran its 2 bytes")
    ]
    garbage = ring_pb2.LogFrame(lognr=6, total_bytes=2, offset=0, data=b"\xff\xff", from_id=0)
    (refusal,) = ReceiverCore(1).frame(garbage)
    assert isinstance(refusal, Refuse) and refusal.code is grpc.StatusCode.INVALID_ARGUMENT
    assert refusal.message.startswith("log message 6 is not a LogMessage: ")


def test_a_rejoin_with_nothing_ends_the_stream_unavailable() -> None:
    assert ReceiverCore(3).dropped() == Refuse(
        grpc.StatusCode.UNAVAILABLE, "controller 3 rejoined the ring with nothing: connect again"
    )


# -- store-and-forward --------------------------------------------------------------


def test_a_whole_message_is_delivered_then_acknowledged() -> None:
    core = ReceiverCore(1, relays=False)
    first, middle, last = parts(1, from_id=2)
    assert feed(core, first) == [Arriving(1)]
    assert feed(core, middle) == [Arriving(1)]
    assert feed(core, last) == [Arriving(1), Deliver(message(1), 2), Ack(1)]


def test_an_abort_frame_mid_message_drops_what_arrived() -> None:
    core = ReceiverCore(1)
    first, middle, _ = parts(1)
    feed(core, first)
    assert core.frame(ring_pb2.LogFrame(lognr=1, abort=True, from_id=0)) == []
    (refusal,) = feed(core, middle)  # nothing of message 1 is held for it to follow
    assert refusal == Refuse(
        grpc.StatusCode.INVALID_ARGUMENT,
        "frame of log message 1 at offset 100 does not follow message None at offset 0",
    )


def test_a_message_given_up_and_sent_again_is_delivered_once_whole() -> None:
    core = ReceiverCore(1)
    feed(core, parts(1)[0])
    core.frame(ring_pb2.LogFrame(lognr=1, abort=True, from_id=0))
    actions = [action for frame in parts(1) for action in feed(core, frame)]
    assert actions == [Arriving(1), Arriving(1), Arriving(1), Deliver(message(1), 0), Ack(1)]


# -- cut-through --------------------------------------------------------------------


def test_a_relayed_message_goes_frame_by_frame_and_is_settled_once_delivered() -> None:
    core = ReceiverCore(1, relays=True)
    first, middle, last = parts(1)
    assert core.frame(first) == [StartRelay(head_of(message(1)), first.total_bytes)]
    assert core.relay_started(True) == [RelayFrame(first), Arriving(1), WaitForRoom()]
    assert feed(core, middle) == [RelayFrame(middle), Arriving(1), WaitForRoom()]
    assert feed(core, last) == [
        RelayFrame(last),
        Arriving(1),
        Deliver(message(1), 0),
        SettleRelay(),
        Ack(1),
    ]
    assert not core.relaying


def test_a_relay_not_started_leaves_the_message_stored_and_forwarded() -> None:
    held = Held()
    core = ReceiverCore(1, relays=True, held=held)
    first, middle, last = parts(1)
    assert feed(core, first, started=False) == [
        StartRelay(head_of(message(1)), first.total_bytes),
        Arriving(1),
    ]
    assert feed(core, middle) == [Arriving(1)]
    assert feed(core, last) == [Arriving(1), Deliver(message(1), 0), Ack(1)]
    assert held.asked == [1, 1]  # asked whether it is held, frame by frame


def test_only_a_first_frame_whose_head_is_what_it_says_starts_a_relay() -> None:
    first = parts(1)[0]
    no_head = ring_pb2.LogFrame()
    no_head.CopyFrom(first)
    no_head.ClearField("head")
    other = ring_pb2.LogFrame()
    other.CopyFrom(first)
    other.head.lognr = 9
    for frame in (no_head, other):
        assert ReceiverCore(1, relays=True).frame(frame) == [Arriving(1)]
    # A driver that never passes messages on is never asked.
    assert ReceiverCore(1, relays=False).frame(first) == [Arriving(1)]


def test_a_new_first_frame_aborts_the_relay_under_way() -> None:
    """Message 1's sender gave it up part-way (it sends message 2's first frame): its
    relay is given up before message 2's starts, and only message 2 is delivered."""
    core = ReceiverCore(1, relays=True)
    one, two = parts(1), parts(2)
    feed(core, one[0])
    feed(core, one[1])
    assert feed(core, two[0]) == [
        AbortRelay(),
        StartRelay(head_of(message(2)), two[0].total_bytes),
        RelayFrame(two[0]),
        Arriving(2),
        WaitForRoom(),
    ]
    feed(core, two[1])
    assert feed(core, two[2])[-3:] == [Deliver(message(2), 0), SettleRelay(), Ack(2)]


def test_a_new_first_frame_without_a_relay_under_way_aborts_nothing() -> None:
    core = ReceiverCore(1, relays=True)
    one, two = parts(1), parts(2)
    feed(core, one[0], started=False)
    assert feed(core, two[0])[0] == StartRelay(head_of(message(2)), two[0].total_bytes)


def test_an_abort_frame_mid_message_aborts_its_relay() -> None:
    core = ReceiverCore(1, relays=True)
    one = parts(1)
    feed(core, one[0])
    feed(core, one[1])
    assert core.frame(ring_pb2.LogFrame(lognr=1, abort=True, from_id=0)) == [AbortRelay()]
    assert not core.relaying
    # Its sender sends it again, whole: a new relay, and one delivery.
    actions = [action for frame in parts(1) for action in feed(core, frame)]
    assert actions.count(AbortRelay()) == 0
    assert [a for a in actions if isinstance(a, Deliver | SettleRelay | Ack)] == [
        Deliver(message(1), 0),
        SettleRelay(),
        Ack(1),
    ]


def test_a_relayed_message_is_never_let_go_as_held() -> None:
    held = Held(True, True, True)
    core = ReceiverCore(1, relays=True, held=held)
    actions = [action for frame in parts(1) for action in feed(core, frame)]
    assert Deliver(message(1), 0) in actions and held.asked == []


def test_relay_started_answers_a_start_relay_only() -> None:
    with pytest.raises(RuntimeError, match="without a StartRelay"):
        ReceiverCore(1, relays=True).relay_started(True)


# -- a copy held already --------------------------------------------------------------


def test_a_copy_held_already_is_counted_not_kept_and_acknowledged_unparsed() -> None:
    """A handover's target gets message 1 straight and round the ring: once the other
    copy came whole, this one's frames are let go and its last acknowledged."""
    held = Held(False, True, True)
    core = ReceiverCore(1, held=held)
    first, middle, last = parts(1)
    assert feed(core, first) == [Arriving(1)]  # not held yet: kept
    assert feed(core, middle) == [Arriving(1)]  # held now: let go
    assert feed(core, last) == [Arriving(1), Ack(1)]  # still held: acknowledged
    assert held.asked == [1, 1, 1]


def test_a_copy_let_go_as_held_and_no_longer_held_is_refused_to_be_sent_again() -> None:
    """The controller rejoined with nothing while it let message 1's frames go: it does
    not acknowledge it; the stream ends and its sender sends it again."""
    core = ReceiverCore(4, held=Held(True))
    first, middle, last = parts(1)
    feed(core, first)
    feed(core, middle)
    assert feed(core, last) == [
        Arriving(1),
        Refuse(
            grpc.StatusCode.UNAVAILABLE,
            "controller 4 let message 1 go as held, and no longer holds it: send it again",
        ),
    ]


def test_a_copy_is_let_go_only_from_its_own_first_frame_on() -> None:
    """The next message's first frame starts over: kept, and delivered, unless held."""
    core = ReceiverCore(1, held=lambda head: head.lognr == 1)
    assert [action for frame in parts(1) for action in feed(core, frame)][-1] == Ack(1)
    actions = [action for frame in parts(2) for action in feed(core, frame)]
    assert actions == [Arriving(2), Arriving(2), Arriving(2), Deliver(message(2), 0), Ack(2)]
