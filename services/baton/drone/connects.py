"""What one Connect stream carries, and when. Pure: the driver writes the events.

A Connect admitted (``Sequencer.admit_connect``) carries, in this order:

1. for the master, the Connected grant, then the replies the drone retains
   above what the controller holds, in batches (``DroneCore.connected``);
   an old master owed a notice gets no grant;
2. then, each time the stream is woken: the operator's pause word when it
   changed since this stream last said it; the PrepareHandover of a
   preparation under way, to the master, once per preparation; and the
   handover notice owed to this controller, after which the stream ends.

The notice is owed until it is written (``DroneCore.delivered``): a stream
that breaks first leaves it for the controller's next Connect.
"""

from __future__ import annotations

from dataclasses import dataclass

from baton.authenticity import Signer, signed_retained
from baton.drone.core import DroneCore
from baton.drone.dedupe import RETAINED_BATCH_BYTES, CachedReply
from baton.v1 import drone_pb2

StreamEvent = drone_pb2.OperatorWord | drone_pb2.PrepareHandover | drone_pb2.HandoverNotice


@dataclass
class ConnectStream:
    """One Connect stream's state: what it already said."""

    controller_id: int
    # Signs the retained replies the drone made (``authenticity.signed_retained``);
    # None: unsigned.
    signer: Signer | None = None
    # The PrepareHandover last sent on it, and the operator's pause as it last told it.
    sent_prepare: drone_pb2.PrepareHandover | None = None
    said_paused: str = ""

    def opened(
        self,
        core: DroneCore,
        request: drone_pb2.ConnectRequest,
        batch_bytes: int = RETAINED_BATCH_BYTES,
    ) -> tuple[drone_pb2.Connected | None, list[list[drone_pb2.RetainedReply]]]:
        """What the stream opened by ``request`` carries first: the grant and the
        retained replies in batches for the master; (None, []) for an old master owed
        a notice."""
        first = core.connected(request, batch_bytes)
        if first is None:
            return None, []
        grant, batches = first
        return grant, [[self._retained(kept) for kept in batch] for batch in batches]

    def _retained(self, kept: CachedReply) -> drone_pb2.RetainedReply:
        return signed_retained(self.signer, kept.to_proto())

    def woken(self, core: DroneCore, operator_words: bool = True) -> list[StreamEvent]:
        """What to write now, in order; a HandoverNotice, if any, is last and ends the
        stream. ``operator_words``: False for a driver whose controllers do not take
        the operator's word on the stream."""
        events: list[StreamEvent] = []
        if operator_words:
            word = core.operator_word()
            if word.paused != self.said_paused:
                events.append(word)
                self.said_paused = word.paused
        while True:
            event = core.stream_event(self.controller_id, self.sent_prepare)
            if event is None:
                return events
            events.append(event)
            if isinstance(event, drone_pb2.HandoverNotice):
                return events
            self.sent_prepare = event
