"""One ring link's send side as a pure object: what it owes its peer, what a new
stream writes, what an acknowledgement releases, and when it says what it holds.

The runtime's ``PeerLink`` (``ring.py``, gRPC streams and frames) and the
simulation's ``RingLink`` (``sim/network.py``, a virtual network) both drive one
``LinkCore``: they turn a stream that opens, breaks or acknowledges into calls
here and write what it returns. Times are arguments; nothing here awaits.

The rules, decided here once:

- A message queued is kept (``Outbox``) until its peer acknowledges it, and
  written on the current stream once; a number queued again is written again
  (its receiver ignores a duplicate by log number and acknowledges it).
- A new stream to a successor (a link that carries the ``history``) first says
  what the history holds (a sync frame), then gives the history above the
  peer's hello (``resend_after``) except what is kept unacknowledged, then the
  unacknowledged messages in log-number order. A stream to any other peer
  (a handover's target) carries only what was queued on it: its "holds 0"
  would tell a restarted new master it had caught up with nothing.
- A successor's stream says what the history holds again whenever the history
  grew past what it said or the master's word changed
  (``ControllerProtocol.master_word``): what the master's predecessor holds,
  every controller holds, which is the watermark the master gives the drone.
- A broken stream forgets what it wrote (the next writes everything kept) and
  tries again after a back-off that doubles up to ``BACKOFF_MAX_S``; a stream
  that comes up starts the back-off over.
- A message being passed on frame by frame (cut-through, ``RelayCore``) is
  written in its log number's turn (``pending``) and may end only once the
  protocol forwarded it whole (``confirm``). A relay given up, or one a stream
  took a frame of and then ended, is not resumed: a frame taken is gone from
  the relay whether or not its write went out (grpc refuses a write on a call
  that finished), and the receiver drops what it got of the message with the
  stream. The message goes whole once forwarded, kept until acknowledged like
  any other (``pending``), or from the history above the next hello.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from baton.controller.history import LogHistory
from baton.controller.outbox import Outbox
from baton.v1 import drone_pb2, ring_pb2

BACKOFF_INITIAL_S = 0.05
BACKOFF_MAX_S = 2.0


@dataclass(frozen=True)
class SyncWord:
    """A sync frame's words: the history holds every message up to ``holds``;
    ``holds_epoch`` is the epoch of its message with that number (a receiver that
    handled a newer one knows this history is of a framing a takeover replaced,
    ``ControllerProtocol.on_sync``); the newest ACTIVE master's epoch and the log
    number it held. On a signed ring, what makes them believed
    (``ControllerCore.sync_arrived``): the proof that the sender holds its message
    ``holds`` (``authenticity.holding_proof``), the drone's grant of ``holds_epoch``
    that message carries, and the master's own signed word."""

    holds: int
    holds_epoch: int
    master_epoch: int
    master_lognr: int
    holds_proof: bytes = b""
    holds_grant: drone_pb2.Grant | None = None
    master_proof: ring_pb2.MasterWord | None = None


@dataclass(frozen=True)
class Greeting:
    """What a stream writes when its peer's hello arrived, in this order: the sync
    word (None: not a successor's stream), the history's messages to give again
    (log numbers), then the unacknowledged ones (``LinkCore.pending``)."""

    sync: SyncWord | None
    from_history: list[int]


@dataclass(frozen=True)
class Acked:
    """What an acknowledgement released: the message (None: not kept, a duplicate's
    acknowledgement) and whether it was a handover message, which enters the
    sender's history only now (``ControllerNode._handover_acked``)."""

    message: ring_pb2.LogMessage | None

    @property
    def handover(self) -> bool:
        """The released message was a handover message with its flag."""
        return self.message is not None and self.message.handover


@dataclass
class PeerCounters:
    """What a link has done, for GetStatus, the benchmarks and a preparation's progress."""

    connects: int = 0
    sent_messages: int = 0
    sent_bytes: int = 0
    acked: int = 0
    relayed_messages: int = 0  # written on frame by frame as they came (cut-through)
    relays_aborted: int = 0  # given up part-way (not forwarded, or a stream broke)
    peak_relay_frames: int = 0  # the most frames a relay held not yet written on


def sync_word(
    history: LogHistory,
    holds: int,
    word: tuple[int, int],
    proof: ring_pb2.MasterWord | None = None,
) -> SyncWord:
    """The sync frame for a history that holds up to ``holds`` and the master's ``word``
    (``proof``: its signed form). A signed message gives its proof of holding and its
    grant; an insecure ring's gives neither."""
    if not (holds and holds in history):
        return SyncWord(holds, 0, *word, master_proof=proof)
    top = history.heading(holds)
    return SyncWord(
        holds,
        top.epoch,
        *word,
        holds_proof=top.proof,
        holds_grant=top.grant if top.proof else None,
        master_proof=proof,
    )


class LinkCore:
    """The send side of one ring link to one peer (the module's rules)."""

    def __init__(self, peer: int, now: float, history: LogHistory | None = None) -> None:
        self.peer = peer
        # The successor's link gives its peer the history; None for other peers.
        self.history = history
        # It carried the history once (``let_history_go``): it still counts as used.
        self.carried_history = history is not None
        # The history's top when the route moved on from this link and it kept the
        # history (``RingLinks.rerouted``); None while it is the successor's.
        self.left_at: int | None = None
        self.outbox = Outbox()
        # Written on the current stream (a new stream writes every unacked one).
        self.sent: set[int] = set()
        self.up = False
        # Since when the stream has not been up; None while it is.
        self.down_since: float | None = now
        self.backoff = BACKOFF_INITIAL_S
        self.counters = PeerCounters()
        # What the last sync frame said: the history's top and the master's word.
        self.synced = 0
        self.synced_word = (0, 0)
        # Messages being passed on frame by frame as they arrive (cut-through).
        self.relays: dict[int, RelayCore] = {}

    # -- events -------------------------------------------------------------------

    def queue(self, message: ring_pb2.LogMessage, now: float) -> None:
        """``message`` is to go to the peer: kept until acknowledged, and written (again,
        if it was written on this stream before) with the next ``pending``."""
        self.outbox.put(message, now)
        self.sent.discard(message.lognr)

    def connected(
        self,
        hello_lognr: int,
        hello_epoch: int,
        word: tuple[int, int],
        proof: ring_pb2.MasterWord | None = None,
    ) -> Greeting:
        """The stream is up and the peer's hello said it handled up to ``hello_lognr``
        (``hello_epoch``: that message's epoch there): what to write first."""
        self.up, self.down_since = True, None
        self.backoff = BACKOFF_INITIAL_S
        self.counters.connects += 1
        self.sent = set()
        history = self.history
        if history is None:
            return Greeting(None, [])
        holds = history.holds_lognr
        self.synced, self.synced_word = holds, word
        ours = history.heading(hello_lognr).epoch if hello_lognr in history else None
        after = self.outbox.resend_from(hello_lognr, hello_epoch, ours)
        again = self.outbox.history_to_resend(history.above(after))
        return Greeting(sync_word(history, holds, word, proof), again)

    def broken(self, now: float) -> float:
        """The stream broke (or never came up): what was written on it is forgotten.
        Returns how long to wait before the next attempt."""
        if self.up or self.down_since is None:
            self.down_since = now
        self.up = False
        self._stream_ended()
        wait, self.backoff = self.backoff, min(self.backoff * 2, BACKOFF_MAX_S)
        return wait

    def restarted(self, now: float) -> None:
        """The driver ended the stream on purpose (it carries a history from now on, or
        the link is stopped): what was written is forgotten, the back-off starts over."""
        if self.up:
            self.down_since = now
        self.up = False
        self._stream_ended()
        self.backoff = BACKOFF_INITIAL_S

    def _stream_ended(self) -> None:
        """What was written on the stream is forgotten, and so is every relay it took a
        frame of (the module's rules): the message goes whole once forwarded."""
        self.sent = set()
        for relay in list(self.relays.values()):
            if relay.taken:
                relay.abort()
                self.relay_given_up(relay)

    def acked(self, lognr: int) -> Acked:
        """The peer acknowledged ``lognr``: the message is released."""
        self.counters.acked += 1
        return Acked(self.outbox.ack(lognr))

    def sync_due(
        self, word: tuple[int, int], proof: ring_pb2.MasterWord | None = None
    ) -> SyncWord | None:
        """The sync frame to write now on an up successor's stream (the history grew, or
        the master's ``word`` changed since the last one; ``proof``: its signed form);
        None: nothing to say."""
        history = self.history
        if history is None or not self.up:
            return None
        holds = history.holds_lognr
        if holds <= self.synced and word == self.synced_word:
            return None
        self.synced, self.synced_word = max(self.synced, holds), word
        return sync_word(history, self.synced, word, proof)

    def pending(self) -> list[int]:
        """What the current stream writes next, in log-number order: the kept messages
        not yet written on it, and the messages being relayed (``relays``; one whose
        relay was given up goes whole if it is kept)."""
        kept = {n for n in self.outbox.unacked if n not in self.sent}
        return sorted(kept | self.relays.keys())

    def relay(self, relay: RelayCore) -> bool:
        """``relay``'s message is to be passed on frame by frame as it arrives; False (not
        taken) if another stream's copy of it is being passed on already."""
        old = self.relays.get(relay.lognr)
        if old is not None and not old.aborted:
            return False
        self.relays[relay.lognr] = relay
        return True

    def relay_written(self, relay: RelayCore) -> None:
        """Every frame of ``relay`` went out on the current stream: its message is written."""
        self._end_relay(relay)
        self.written(relay.lognr)
        self.counters.relayed_messages += 1

    def relay_given_up(self, relay: RelayCore) -> None:
        """``relay`` was aborted: its message goes whole if it is forwarded."""
        self._end_relay(relay)
        self.counters.relays_aborted += 1

    def _end_relay(self, relay: RelayCore) -> None:
        # Another stream's copy may have taken an aborted relay's place meanwhile.
        if self.relays.get(relay.lognr) is relay:
            del self.relays[relay.lognr]

    def written(self, lognr: int) -> None:
        """Message ``lognr`` went out whole on the current stream (kept, from the history
        or relayed)."""
        self.sent.add(lognr)
        self.counters.sent_messages += 1

    def settle_handovers(self, settled: Callable[[int], bool]) -> list[ring_pb2.LogMessage]:
        """``Outbox.settle_handovers``: settled handover messages kept from now on without
        their flag (returned as they were). Written on this stream already, they are not
        written again."""
        return self.outbox.settle_handovers(settled)

    # -- what it holds --------------------------------------------------------------

    @property
    def unacked(self) -> dict[int, ring_pb2.LogMessage]:
        """The messages sent and not yet acknowledged, by log number."""
        return self.outbox.unacked

    @property
    def used(self) -> bool:
        """Whether the link carries anything: the successor's now or before, or one a
        message was sent on (not only kept open for a handover to come). A successor's
        routed away from stays used: its stream being down is what the route reads, and
        taken for a link never tried it would be routed back to at once, for ever."""
        return self.carried_history or bool(self.outbox.unacked) or self.counters.sent_messages > 0

    def carry_history(self, history: LogHistory) -> None:
        """This link is the successor's now: it gives its peer ``history``."""
        self.history = history
        self.carried_history = True

    def let_history_go(self) -> None:
        """The route moved on from this link: it carries only what it owes."""
        self.history = None


class RelayCore:
    """One log message's frames passed on to a peer as they arrive (cut-through).

    The receiving stream adds each frame; the peer's link takes them as they
    may go (``ready``). The last frame waits for ``confirm`` (the protocol
    forwarded the whole message); ``settle`` without it, or ``abort``, and the
    peer is told to drop what it got.
    """

    def __init__(self, lognr: int, total_bytes: int) -> None:
        self.lognr = lognr
        self.total_bytes = total_bytes
        self.frames: deque[ring_pb2.LogFrame] = deque()
        self.received = 0
        self.confirmed = False
        self.aborted = False
        # Frames taken off to be written (``ready``): a stream that ends after taking
        # one ends the relay (``LinkCore._stream_ended``).
        self.taken = 0
        # Written on the stream, bytes and frames.
        self.written = 0
        self.frames_written = 0
        self.peak_buffered = 0

    def add(self, frame: ring_pb2.LogFrame) -> None:
        """A frame of the message arrived (in order: the Reassembler checked it)."""
        self.frames.append(frame)
        self.received += len(frame.data)
        self.peak_buffered = max(self.peak_buffered, len(self.frames))

    def confirm(self) -> None:
        """The protocol forwarded the whole message to this peer: the last frame may go."""
        self.confirmed = True

    def settle(self) -> None:
        """The whole message was handled: unless confirmed, it is not forwarded."""
        if not self.confirmed:
            self.abort()

    def abort(self) -> None:
        """The message is not passed on (its stream broke, or it is not forwarded)."""
        self.aborted = True

    def ready(self) -> ring_pb2.LogFrame | None:
        """The next frame that may be written now, taken off the relay."""
        if not self.frames or self.aborted:
            return None
        last = len(self.frames) == 1 and self.received >= self.total_bytes
        if last and not self.confirmed:
            return None
        self.taken += 1
        return self.frames.popleft()

    def wrote(self, frame: ring_pb2.LogFrame) -> None:
        """``frame`` went out on the stream."""
        self.written += len(frame.data)
        self.frames_written += 1

    @property
    def done(self) -> bool:
        """Every frame was written: the message went whole."""
        return self.frames_written > 0 and self.written >= self.total_bytes
