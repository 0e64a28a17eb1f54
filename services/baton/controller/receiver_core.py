"""The receiving end of one LogRing stream as a pure object: frames in, actions out.

The runtime's ``RingReceiver`` (``ring.py``) reads a stream's frames, feeds each
to one ``ReceiverCore`` and carries out the actions it returns; what the
stream refuses, which message it delivers or acknowledges, and when a
message is passed on as it comes (cut-through) is decided here. No asyncio,
no gRPC calls (its status codes name a refusal), no clock. Two questions are
asked of the caller, synchronously: whether a message is held already
(``held``, given a head: ``ControllerProtocol.holds``), and, through the
``StartRelay`` action, whether a relay was started.

The rules:

- Every frame must say it comes from the controller the stream's certificate
  names (``sender``, on a mutual-TLS ring); another is refused
  (PERMISSION_DENIED) before anything of it is taken.
- A sync frame says what its sender holds (``Synced``); it is not part of a
  message.
- A message's first frame carries its head. If the driver may pass messages
  on (``relays``) and the head is what the frame says (its log number, a size
  within ``max_bytes``), the driver is asked to start a relay
  (``StartRelay``); the relay then gets every frame as it arrives, and the
  stream waits while the relay's window is full (``WaitForRoom``).
- A first frame while a message is part-way through, or an abort frame, ends
  that message: its sender gave it up, and so does its relay (``AbortRelay``).
- A frame that does not follow, a size above ``max_bytes`` or an overrun, and
  a message that does not parse are refused (INVALID_ARGUMENT, the
  ``Reassembler``'s words).
- A message whose copy is held already (the other copy, straight from an old
  master or round the ring, came whole meanwhile) is let go part-way: the
  rest of its frames are counted, not kept, and its last frame acknowledged
  without parsing it. If it is no longer held then (the controller rejoined
  with nothing meanwhile), it is refused (UNAVAILABLE): its sender sends it
  again on its next stream.
- A whole message is delivered, its relay settled (``RelayCore.settle``: its
  last frame goes only if the protocol forwarded it), then acknowledged.

The order of one frame's actions, applied front to back (a step may await):

1. ``Refuse(code, message)``: the stream ends with that status; nothing after
   it is applied (it is last of its list).
2. ``Synced(sender, word)``: alone, for a sync frame.
3. ``AbortRelay``: for an abort frame (alone) or a first frame while a relay
   is under way.
4. ``StartRelay(head, total_bytes)``, last of its list: the driver asks for a
   relay and answers ``relay_started(started)``, whose actions (5 to 7)
   continue the frame's.
5. ``RelayFrame(frame)``, then ``Arriving(lognr)`` (a message on its way is
   not missing: ``ControllerCore.gap_due``).
6. A message not yet whole: ``WaitForRoom`` if it is relayed.
7. A whole message: ``Deliver(message, relayed_by)``, ``SettleRelay`` if it is
   relayed, ``Ack(lognr)``; a copy let go as held: ``Ack(lognr)``, or
   ``Refuse`` if it is no longer held.

However the stream ends (its sender closed it, a refusal, ``drop_streams``,
an error), the driver aborts the relay it holds, if any: one started and
neither aborted nor settled is of a message that never came whole.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import grpc
from google.protobuf.message import DecodeError

from baton.config import MAX_LOG_MESSAGE_DEFAULT
from baton.controller.link_core import SyncWord
from baton.v1 import ring_pb2


def sync_word_of(frame: ring_pb2.LogFrame) -> SyncWord:
    """What a sync frame says (``ring._sync_frame`` read back)."""
    return SyncWord(
        frame.holds_lognr,
        frame.holds_epoch,
        frame.master_epoch,
        frame.master_lognr,
        frame.holds_proof,
        frame.holds_grant if frame.HasField("holds_grant") else None,
        frame.master_word if frame.HasField("master_word") else None,
    )


@dataclass(frozen=True)
class Skipped:
    """A message whose frames were counted, not kept (``Reassembler.skip``): complete."""

    lognr: int


class Reassembler:
    """Puts frames back together into whole log messages, checking their order and size.

    ``max_bytes`` bounds a message (the configuration's max_log_message): a
    first frame claiming more is refused before anything is buffered.
    """

    def __init__(self, max_bytes: int = MAX_LOG_MESSAGE_DEFAULT) -> None:
        self.max_bytes = max_bytes
        self._lognr: int | None = None
        self._parts: list[bytes] = []
        self._received = 0
        self._skipping = False

    def drop(self, lognr: int) -> None:
        """Forgets what arrived of message ``lognr`` (its sender gave it up)."""
        if self._lognr == lognr:
            self._lognr, self._parts, self._received = None, [], 0

    def skip(self, lognr: int) -> None:
        """Message ``lognr``, part-way through, is held already (its other copy came
        whole): what arrived is let go, the rest only counted, and its last frame
        gives ``Skipped`` rather than a message parsed for nothing."""
        if self._lognr == lognr:
            self._parts, self._skipping = [], True

    def add(self, frame: ring_pb2.LogFrame) -> ring_pb2.LogMessage | Skipped | None:
        """Adds a frame; returns the message when its last frame arrived."""
        if frame.total_bytes > self.max_bytes:
            raise ValueError(
                f"log message {frame.lognr} claims {frame.total_bytes} bytes, above "
                f"max_log_message ({self.max_bytes} bytes); raise it in the testbed file if "
                "missions log larger entries"
            )
        if frame.offset == 0:
            self._lognr, self._parts, self._received = frame.lognr, [], 0
            self._skipping = False
        elif frame.lognr != self._lognr or frame.offset != self._received:
            raise ValueError(
                f"frame of log message {frame.lognr} at offset {frame.offset} does not follow "
                f"message {self._lognr} at offset {self._received}"
            )
        if not self._skipping:
            self._parts.append(frame.data)
        self._received += len(frame.data)
        if self._received < frame.total_bytes:
            return None
        if self._received > frame.total_bytes:
            raise ValueError(f"log message {frame.lognr} overran its {frame.total_bytes} bytes")
        data = b"".join(self._parts)
        self._lognr, self._parts, self._received = None, [], 0
        if self._skipping:
            self._skipping = False
            return Skipped(frame.lognr)
        try:
            return ring_pb2.LogMessage.FromString(data)
        except DecodeError as exc:  # a malformed frame names itself (test_fuzz_ring.py)
            raise ValueError(f"log message {frame.lognr} is not a LogMessage: {exc}") from None


# -- actions (the module's order) -------------------------------------------------


@dataclass(frozen=True)
class Hello:
    """Write the stream's hello: we handled every message up to ``lognr``, whose epoch
    is ``epoch`` here (0: none held)."""

    lognr: int
    epoch: int


@dataclass(frozen=True)
class Refuse:
    """End the stream with ``code`` and ``message``; nothing after it is applied."""

    code: grpc.StatusCode
    message: str


@dataclass(frozen=True)
class Synced:
    """Controller ``sender``'s sync frame says ``word`` (``ControllerCore.sync_arrived``)."""

    sender: int
    word: SyncWord


@dataclass(frozen=True)
class StartRelay:
    """Ask for a relay passing the message of ``head`` (``total_bytes`` long) on as its
    frames arrive, and answer ``ReceiverCore.relay_started``."""

    head: ring_pb2.LogMessage
    total_bytes: int


@dataclass(frozen=True)
class RelayFrame:
    """Add ``frame`` to the relay under way."""

    frame: ring_pb2.LogFrame


@dataclass(frozen=True)
class AbortRelay:
    """Give up the relay under way: its message did not come whole on this stream."""


@dataclass(frozen=True)
class SettleRelay:
    """The relayed message was delivered: settle its relay (``RelayCore.settle``)."""


@dataclass(frozen=True)
class WaitForRoom:
    """Wait while the relay under way holds a full window (``Relay.room``)."""


@dataclass(frozen=True)
class Arriving:
    """A frame of message ``lognr`` arrived: it is on its way, not missing."""

    lognr: int


@dataclass(frozen=True)
class Deliver:
    """Hand a whole ``message`` to the controller (``ControllerNode.on_log``), as relayed
    by controller ``relayed_by``."""

    message: ring_pb2.LogMessage
    relayed_by: int


@dataclass(frozen=True)
class Ack:
    """Acknowledge message ``lognr`` to the sender."""

    lognr: int


Action = (
    Refuse
    | Synced
    | AbortRelay
    | StartRelay
    | RelayFrame
    | Arriving
    | WaitForRoom
    | Deliver
    | SettleRelay
    | Ack
)

ABORT_RELAY = AbortRelay()
SETTLE_RELAY = SettleRelay()
WAIT_FOR_ROOM = WaitForRoom()


class ReceiverCore:
    """The receiving end of one LogRing stream (the module's rules).

    ``my_id``: this controller, named in refusals. ``sender``: the controller the
    stream's certificate names (None: not checked). ``relays``: whether the driver
    may pass messages on (``StartRelay``). ``held``: given a message's head, whether
    handling it whole would do nothing (None: never).
    """

    def __init__(
        self,
        my_id: int,
        sender: int | None = None,
        max_bytes: int = MAX_LOG_MESSAGE_DEFAULT,
        relays: bool = False,
        held: Callable[[ring_pb2.LogMessage], bool] | None = None,
    ) -> None:
        self.my_id = my_id
        self.sender = sender
        self.relays = relays
        self._held = held
        self._reassembler = Reassembler(max_bytes)
        # The head (from its first frame) of the message part-way through.
        self._head: ring_pb2.LogMessage | None = None
        # Whether a relay of that message is under way (started, not aborted or settled).
        self.relaying = False
        # A first frame whose relay the driver was asked for (``relay_started``).
        self._asked: ring_pb2.LogFrame | None = None

    # -- events -------------------------------------------------------------------

    def opened(self, holds_lognr: int, epoch_of: Callable[[int], int] | None = None) -> Hello:
        """The stream opened: the hello says we handled every message up to
        ``holds_lognr``, and that message's epoch (``epoch_of``; 0 when none is held)."""
        epoch = epoch_of(holds_lognr) if epoch_of is not None and holds_lognr else 0
        return Hello(holds_lognr, epoch)

    def frame(self, frame: ring_pb2.LogFrame) -> list[Action]:
        """A frame arrived: what to do, in the module's order."""
        if self.sender is not None and frame.from_id != self.sender:
            return [
                Refuse(
                    grpc.StatusCode.PERMISSION_DENIED,
                    f"LogRing: controller {self.sender}'s certificate sent a frame from_id "
                    f"{frame.from_id}; a controller sends its own frames only",
                )
            ]
        if frame.sync:
            return [Synced(frame.from_id, sync_word_of(frame))]
        if frame.abort:
            self._reassembler.drop(frame.lognr)
            return self._end_relay(ABORT_RELAY)
        if frame.offset != 0:
            return self._take(frame, [])
        # A new message: the one part-way through, if any, was given up.
        actions = self._end_relay(ABORT_RELAY)
        self._head = frame.head if frame.HasField("head") else None
        if self._may_relay(frame):
            self._asked = frame
            actions.append(StartRelay(frame.head, frame.total_bytes))
            return actions
        return self._take(frame, actions)

    def relay_started(self, started: bool) -> list[Action]:
        """The answer to ``StartRelay``: whether a relay passes the message on. Returns
        the rest of its first frame's actions."""
        frame, self._asked = self._asked, None
        if frame is None:
            raise RuntimeError("relay_started without a StartRelay to answer")
        self.relaying = started
        return self._take(frame, [])

    def undecodable(self, error: Exception) -> list[Action]:
        """What arrived is not a LogFrame (``error``: the parser's words)."""
        return [
            Refuse(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"LogRing: a frame that is not a LogFrame ({error}); nothing of it was taken",
            )
        ]

    def dropped(self) -> Refuse:
        """Every incoming stream ends (``RingReceiver.drop_streams``): its sender connects
        again and hears our hello."""
        return Refuse(
            grpc.StatusCode.UNAVAILABLE,
            f"controller {self.my_id} rejoined the ring with nothing: connect again",
        )

    # -- the steps ----------------------------------------------------------------

    def _may_relay(self, first: ring_pb2.LogFrame) -> bool:
        """Whether the message whose first frame this is may be passed on as it comes:
        not one the reassembler refuses, nor one whose head is not what the frame says."""
        return (
            self.relays
            and first.HasField("head")
            and first.total_bytes <= self._reassembler.max_bytes
            and first.head.lognr == first.lognr
        )

    def _end_relay(self, end: AbortRelay | SettleRelay) -> list[Action]:
        if not self.relaying:
            return []
        self.relaying = False
        return [end]

    def _take(self, frame: ring_pb2.LogFrame, actions: list[Action]) -> list[Action]:
        """A frame of the message part-way through (or its first): reassembled, passed
        on, and the message delivered or acknowledged once whole."""
        try:
            message = self._reassembler.add(frame)
        except ValueError as exc:
            actions.append(Refuse(grpc.StatusCode.INVALID_ARGUMENT, str(exc)))
            return actions
        if self.relaying:
            actions.append(RelayFrame(frame))
        actions.append(Arriving(frame.lognr))
        if message is None:
            if self.relaying:
                actions.append(WAIT_FOR_ROOM)
            elif self._holds():
                self._reassembler.skip(frame.lognr)
            return actions
        if isinstance(message, Skipped):
            if self._holds():
                actions.append(Ack(message.lognr))
            else:  # we rejoined with nothing meanwhile
                actions.append(
                    Refuse(
                        grpc.StatusCode.UNAVAILABLE,
                        f"controller {self.my_id} let message {message.lognr} go as held, "
                        "and no longer holds it: send it again",
                    )
                )
            return actions
        actions.append(Deliver(message, frame.from_id))
        actions.extend(self._end_relay(SETTLE_RELAY))
        actions.append(Ack(message.lognr))
        return actions

    def _holds(self) -> bool:
        head = self._head
        return head is not None and self._held is not None and self._held(head)
