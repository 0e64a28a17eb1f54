"""What one ring link owes its peer, as a pure object: the messages sent and not yet
acknowledged, and which of the history a new stream must give again.

The runtime's ``PeerLink`` (``ring.py``) and the simulation's ``RingLink`` both keep
one: the rules below are decided here once.

- A message is kept until its receiver acknowledges it, and written again on every
  new stream (its receiver ignores a duplicate by log number and acknowledges it).
- A new stream first gives the receiver what the history holds above its hello
  (``resend_after``: from the hello's own number when ours is of a newer epoch),
  except what is kept unacknowledged, which follows in order.
- A handover message whose role is settled (the ring went on past it) is written
  from then on without its flag: its receiver may be a fresh self that handled it
  and handed the role on, and the flag would make it master again in an epoch
  long over. The message as it was goes to the caller's history, as on an
  acknowledgement.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

from baton.controller.protocol import resend_after
from baton.v1 import ring_pb2


class Outbox:
    """The unacknowledged messages to one peer, and what a new stream re-sends."""

    def __init__(self) -> None:
        self.unacked: dict[int, ring_pb2.LogMessage] = {}
        # When each unacknowledged message was first sent (the caller's clock).
        self.sent_at: dict[int, float] = {}

    def put(self, message: ring_pb2.LogMessage, now: float) -> None:
        """``message`` is sent: kept until acknowledged (a number sent before replaces
        its message, and keeps its first send time)."""
        self.unacked[message.lognr] = message
        self.sent_at.setdefault(message.lognr, now)

    def ack(self, lognr: int) -> ring_pb2.LogMessage | None:
        """The receiver acknowledged ``lognr``: the message it was (None: not kept)."""
        self.sent_at.pop(lognr, None)
        return self.unacked.pop(lognr, None)

    def settle_handovers(self, settled: Callable[[int], bool]) -> list[ring_pb2.LogMessage]:
        """Our unacknowledged handover messages whose role is ``settled``
        (``ControllerProtocol.handover_settled``), kept from now on without the flag;
        returns them as they were."""
        done: list[ring_pb2.LogMessage] = []
        for lognr, message in sorted(self.unacked.items()):
            if not message.handover or not settled(lognr):
                continue
            plain = ring_pb2.LogMessage()
            plain.CopyFrom(message)
            plain.handover = False
            self.unacked[lognr] = plain
            done.append(message)
        return done

    def resend_from(self, hello_lognr: int, hello_epoch: int, ours: int | None) -> int:
        """Above which log number a new stream gives the history again (``resend_after``:
        ``ours`` is the epoch of our message with the hello's number, None: none)."""
        return resend_after(hello_lognr, hello_epoch, ours)

    def history_to_resend(self, above: Iterable[int]) -> list[int]:
        """Of the history's log numbers ``above`` the resend point, those a new stream
        writes before the unacknowledged ones: all but those kept unacknowledged."""
        return [lognr for lognr in above if lognr not in self.unacked]

    def waiting_for_ack_s(self, now: float) -> float:
        """How long the oldest unacknowledged message has waited (0: none waits)."""
        return now - min(self.sent_at.values()) if self.sent_at else 0.0

    @property
    def unacked_bytes(self) -> int:
        """The serialized size of the messages sent and not yet acknowledged."""
        return sum(message.ByteSize() for message in self.unacked.values())
