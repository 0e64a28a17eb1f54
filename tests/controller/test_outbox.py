"""What a ring link owes its peer (the pure Outbox both the runtime's and the
simulation's links keep)."""

from __future__ import annotations

from baton.controller.outbox import Outbox
from baton.v1 import ring_pb2


def message(lognr: int, handover: bool = False) -> ring_pb2.LogMessage:
    return ring_pb2.LogMessage(lognr=lognr, origin=0, handover=handover)


def test_a_message_is_kept_until_acknowledged_and_its_first_send_time_counts() -> None:
    box = Outbox()
    box.put(message(1), now=10.0)
    box.put(message(2), now=11.0)
    box.put(message(1), now=12.0)  # written again: keeps its first time
    assert box.waiting_for_ack_s(13.0) == 3.0
    assert box.ack(1) is not None and box.ack(1) is None
    assert sorted(box.unacked) == [2] and box.waiting_for_ack_s(13.0) == 2.0
    assert box.unacked_bytes == message(2).ByteSize()


def test_a_new_stream_resends_the_history_but_what_is_kept_unacknowledged() -> None:
    box = Outbox()
    box.put(message(5), now=0.0)
    assert box.history_to_resend([3, 4, 5, 6]) == [3, 4, 6]
    # From the hello's own number when ours is of a newer epoch (resend_after).
    assert box.resend_from(4, hello_epoch=1, ours=2) == 3
    assert box.resend_from(4, hello_epoch=2, ours=2) == 4


def test_a_settled_handover_is_kept_without_its_flag_once() -> None:
    box = Outbox()
    box.put(message(1, handover=True), now=0.0)
    box.put(message(2), now=0.0)
    assert box.settle_handovers(lambda lognr: False) == []
    (settled,) = box.settle_handovers(lambda lognr: True)
    assert settled.handover and settled.lognr == 1
    assert not box.unacked[1].handover
    assert box.settle_handovers(lambda lognr: True) == []
