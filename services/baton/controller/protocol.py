"""Algorithm 1 of the paper as a pure state machine: messages in, effects out.

No sockets, no tasks, no clocks: the controller runtime (``node.py``) feeds
events in (a drone reply, a handover notice, a log message, a replayed call)
and carries out the effects that come back (send a log message, open or close
the drone connection). Every corner of the protocol is therefore testable by
feeding events in a chosen order (``tests/controller/test_protocol.py``).

Names follow Algorithm 1: ``state``, ``master``, ``reqnr``, ``lognr``,
``log``, ``logQ`` (``log_queue``), ``nxtid`` (``successor``), flush limit.
Where docs/design.md reads the paper's text over its pseudo-code, the method says so.
"""

from __future__ import annotations

import enum
import hashlib
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

from baton.authenticity import proof_of
from baton.controller.mastership import Mastership, State
from baton.digest import request_digest
from baton.rpc.methods import describe_nondeterminism
from baton.v1 import drone_pb2, ring_pb2


@dataclass(frozen=True)
class SendLog:
    """Effect: send ``message`` to controller ``dest`` over the ring RPC."""

    dest: int
    message: ring_pb2.LogMessage
    # A copy of a message also sent to the successor (to a prepared handover's
    # target): held once, with the successor's.
    copy: bool = False
    # Our own message's ``authenticity.holding_proof``, computed with its signature
    # (b"": unsigned, or not computed): the history keeps it for the sync words.
    proof: bytes = b""


@dataclass(frozen=True)
class ConnectDrone:
    """Effect: open the drone connection (connectToDrone in Algorithm 1)."""


@dataclass(frozen=True)
class DisconnectDrone:
    """Effect: close the drone connection (the controller stopped being ACTIVE)."""


@dataclass(frozen=True)
class TookOver:
    """Effect (bookkeeping only): a handover message made this controller master."""

    old_master: int
    lognr: int
    reqnr: int
    message_bytes: int


@dataclass(frozen=True)
class ReplacedFraming:
    """The first request a taker holds in a framing a later mastership replaced
    (``ControllerProtocol.replaced_framing``), and where that framing begins.

    From log message ``lognr`` on (the one that holds ``reqnr`` in our
    framing, of ``ours_epoch``) ours is not the drone's; the drone's outcome
    of ``reqnr`` was brought in ``epoch``. The taker rejoins refusing that
    framing from there on (``ControllerProtocol.refuse_replaced``):
    docs/design.md, "A taker that holds a replaced framing". ``reqnr`` 0: the
    drone's grant named the framing by its log numbers (``Connected.
    replaced_from_lognr``), every epoch up to ``ours_epoch`` refused there.
    """

    reqnr: int
    lognr: int
    ours_epoch: int
    epoch: int


@dataclass(frozen=True)
class Fenced:
    """Effect (bookkeeping only): a log message from a master the drone has fenced, dropped."""

    lognr: int
    origin: int
    epoch: int


@dataclass(frozen=True)
class Diverged:
    """Effect: a message numbered like one we handled, from a newer epoch: a takeover
    framed the same replies differently. We must rejoin with nothing (docs/design.md)."""

    lognr: int
    ours_epoch: int
    ring_epoch: int


@dataclass(frozen=True)
class Unqueued:
    """Effect: a queued message of a framing a takeover replaced (older than one handled
    or queued below it), dropped unhandled: out of the history too, since the ring's
    message with its number is to be taken (``ControllerProtocol._drop_stale_queued``)."""

    lognr: int
    origin: int
    epoch: int


Effect = SendLog | ConnectDrone | DisconnectDrone | TookOver | Fenced | Diverged | Unqueued

# Log numbers whose epoch a controller remembers, the newest (a takeover's
# renumbering is found among the last few messages, never thousands back).
EPOCHS_KEPT = 4096


class _Outcome(Protocol):
    """What a program saw of a request: a log entry's, or a reply the drone retains."""

    @property
    def request_digest(self) -> bytes: ...
    @property
    def reply(self) -> bytes: ...
    @property
    def status_code(self) -> int: ...
    @property
    def given_up(self) -> bool: ...


def seen_as(outcome: _Outcome) -> tuple[bytes, int, bool, bytes]:
    """An outcome, to compare: the request, status, give-up and reply (by digest)."""
    reply = hashlib.sha256(outcome.reply).digest()
    return outcome.request_digest, outcome.status_code, outcome.given_up, reply


class _Arrival(enum.Enum):
    """What an arriving log message is to a controller (``ControllerProtocol._arrival``)."""

    DIVERGED = "diverged"  # a takeover's framing of a number we hold: rejoin
    FENCED = "fenced"  # from a master the drone replaced: neither held nor forwarded
    REPLACES_QUEUED = "replaces queued"  # a newer framing of a queued number
    OURS_PASSED = "ours passed"  # our handover message, back after the ring went past it
    SEEN = "seen"  # a re-send of one we received: ignored
    NEW = "new"  # forwarded, then handled or queued


# The arrivals ``on_log`` forwards.
_FORWARDED = frozenset({_Arrival.REPLACES_QUEUED, _Arrival.OURS_PASSED, _Arrival.NEW})


class Refusal(enum.Enum):
    """What a drone refusal that names a master means to the controller that sent the request."""

    STALE = "stale"  # from an earlier ACTIVE period: ignore it, nothing was executed
    HANDED_OVER = "handed over"  # another master now: a handover notice
    DISAGREE = "disagree"  # ourselves, now, refusing the number: the log and drone disagree
    REGRANTED = "regranted"  # ourselves in a newer epoch: the role went and came back unheard


class NonDeterminismError(Exception):
    """The mission program asked for something other than what the log holds."""

    def __init__(self, reqnr: int, logged: ring_pb2.LogEntry, method: str, request: bytes) -> None:
        self.reqnr = reqnr
        self.logged_method = logged.method
        self.logged_request = bytes(logged.request)
        self.method = method
        self.request = request
        super().__init__(
            describe_nondeterminism(reqnr, logged.method, bytes(logged.request), method, request)
        )


def ring_route(
    ring: list[int],
    me: int,
    down_for: Callable[[int], float | None],
    detection_s: float,
    current: int | None = None,
) -> tuple[int, list[int]]:
    """Where ``me`` sends the ring's messages, and which successors it skips.

    The first controller after ``me`` in ring order whose stream has not
    been down for ``detection_s`` (``down_for``: seconds down, 0 while up,
    None if no stream to it was tried yet, which makes it the one to try);
    if every one is down, the one we send to now (``current``; the natural
    successor if None). docs/design.md, "The ring routes around the dead".

    Not the natural successor whenever every one is down: a stream counts
    as down from its first attempt, so one whose set-up takes longer than
    the detection time (a slow direction) is down for it before it can
    come up; going back to a dead natural successor would drop that stream
    and try it again from nothing, for ever, and the controllers after us
    (a taker among them) would never be given the log.
    """
    position = ring.index(me)
    order = [ring[(position + step) % len(ring)] for step in range(1, len(ring))]
    for k, candidate in enumerate(order):
        down = down_for(candidate)
        if down is None or down < detection_s:
            return candidate, order[:k]
    if current in order:
        return current, order[: order.index(current)]
    return order[0], []


def resend_after(hello_lognr: int, hello_epoch: int, our_epoch: int | None) -> int:
    """The log number above which a ring sender gives a receiver its history.

    The receiver's hello says the log number it holds (``hello_lognr``) and
    the epoch its message with that number was logged in (``hello_epoch``,
    0 if unknown); ``our_epoch`` is the epoch of the sender's own message
    with that number (None if it holds none). A newer one means a takeover
    numbered the log again after the receiver's message was framed (it never
    left a master that was lost or fenced): the sender gives that message
    too, and the receiver, seeing the ring's message with its number and a
    newer epoch, rejoins (``Diverged``). Without it, a receiver whose top
    message was renumbered would hear only what lies above it and never
    learn that it diverged.
    """
    if hello_lognr > 0 and our_epoch is not None and 0 < hello_epoch < our_epoch:
        return hello_lognr - 1
    return hello_lognr


class SeenNumbers:
    """A set of positive integers kept as a watermark plus the few above it.

    Every number up to ``upto`` was seen; ``above`` holds those seen beyond
    a gap. Log messages arrive nearly in order, so this stays a few numbers
    for a whole mission, where a plain set grew by one per message.
    """

    def __init__(self) -> None:
        self.upto = 0
        self.above: set[int] = set()

    def __contains__(self, number: object) -> bool:
        return isinstance(number, int) and (number <= self.upto or number in self.above)

    def __len__(self) -> int:
        """Numbers kept beyond the watermark (what this costs in memory)."""
        return len(self.above)

    def discard(self, number: int) -> None:
        """Forgets ``number`` (a message dropped unhandled: another copy must be taken).

        Below the watermark, the numbers above it go back to ``above``: only
        queued messages are dropped, so they are few."""
        if number <= self.upto:
            self.above.update(range(number + 1, self.upto + 1))
            self.upto = number - 1
        self.above.discard(number)

    def add(self, number: int) -> None:
        """Notes ``number``; moves the watermark over every number now contiguous."""
        if number <= self.upto:
            return
        self.above.add(number)
        while self.upto + 1 in self.above:
            self.above.remove(self.upto + 1)
            self.upto += 1


class ProtocolError(Exception):
    """A message that breaks the protocol's invariants (a bug or a misconfiguration).

    ``effects`` are what must still be carried out (the forward of the
    message that could not be handled, so the replicas after this one are
    not starved by its failure).
    """

    def __init__(self, text: str, effects: list[Effect] | None = None) -> None:
        super().__init__(text)
        self.effects: list[Effect] = list(effects or [])


Sealable = ring_pb2.LogMessage | ring_pb2.MasterWord


def _unsealed(message: Sealable) -> bytes:
    """An insecure ring's seal: the message goes unsigned (nothing signed)."""
    return b""


def entry_size(entry: ring_pb2.LogEntry) -> int:
    """Bytes that ``entry`` adds to a serialized log message (field tag and length included).

    ``LogMessage.entries`` is field 4, so its tag is one byte; the length is a
    varint. Computed rather than measured on a one-entry ``LogMessage``, which
    copied the entry (its reply: a picture) on every append and every replayed
    call (``tests/bench/test_model.py`` holds the two equal).
    """
    size = entry.ByteSize()
    return 1 + _varint_size(size) + size


def _varint_size(value: int) -> int:
    """Bytes of ``value`` (>= 0) as a protobuf varint."""
    return max(1, (value.bit_length() + 6) // 7)


@dataclass
class Log:
    """The master's log: entries since the last flush, and their serialized size."""

    entries: deque[ring_pb2.LogEntry] = field(default_factory=deque)
    size: int = 0

    def append(self, entry: ring_pb2.LogEntry) -> None:
        """Adds an entry (Algorithm 1, line 15)."""
        self.entries.append(entry)
        self.size += entry_size(entry)

    def take(self) -> list[ring_pb2.LogEntry]:
        """Empties the log and returns what it held."""
        entries, self.entries, self.size = list(self.entries), deque(), 0
        return entries

    def pop_first(self) -> ring_pb2.LogEntry:
        """Removes and returns the oldest entry (replay consumes the log from the front)."""
        entry = self.entries.popleft()
        self.size -= entry_size(entry)
        return entry

    def __len__(self) -> int:
        return len(self.entries)


class ControllerProtocol:
    """One controller's Algorithm 1 state.

    ``ring`` is the ring order of controller ids; ``flush_limit`` is f in
    bytes (0 flushes after every call). The paper's initial master n_0 is
    the drone's to say: it grants it epoch 1 (``on_granted``).
    """

    def __init__(self, cid: int, ring: list[int], flush_limit: int) -> None:
        if cid not in ring:
            raise ValueError(f"controller {cid} is not in the ring {ring}")
        if flush_limit < 0:
            raise ValueError(f"flush limit must be >= 0 bytes, got {flush_limit}")
        self.id = cid
        self.ring = list(ring)
        self.flush_limit = flush_limit
        # Signs each log message we create once it is whole (``Signer.seal``, with this
        # controller's key: baton.authenticity); a no-op on an insecure ring.
        self.seal: Callable[[Sealable], bytes] = _unsealed
        # The target of the prepared handover under way (``on_prepare``), if any.
        self.preparing_for: int | None = None
        # The mission program ended (``on_mission_done``): an entry logged since (a
        # call it gave up on, settled once ACTIVE again) is flushed at once.
        self.mission_over = False
        position = ring.index(cid)
        self.predecessor = ring[(position - 1) % len(ring)]  # prvid
        self.successor = ring[(position + 1) % len(ring)]  # nxtid
        # Lines 2-10.
        self.reqnr = 0
        self.lognr = 0
        self.log = Log()
        self.log_queue: dict[int, ring_pb2.LogMessage] = {}  # logQ, ordered by lognr
        # A handover message whose log number diverged from ours (on_log): kept for
        # the controller's fresh self (``kept_for_rejoin``).
        self._diverging_handover: ring_pb2.LogMessage | None = None
        # Our handover message's log number, counted as received when the ring went
        # on past it before it came back (on_log): forwarded if it comes.
        self._passed_handed = 0
        # The newest epoch of a log message handled, and the epoch whose handover
        # message a cooperative grant owes us (on_granted, caught_up).
        self._handled_epoch = 0
        self._owed_epoch = 0
        # The epoch of the takeover that fenced us (on_fenced): older handover
        # messages are not kept for the rejoin.
        self._fenced_in = 0
        # Fenced (``on_fenced``): this state is given up; the runtime rejoins with a
        # fresh one, and until then nothing queued is handled here.
        self.fenced = False
        # Not ACTIVE on our own word (docs/design.md, "Restarts"): every
        # controller starts PASSIVE and asks the drone, which grants the
        # initial master epoch 1 at the mission's start, or tells a restarted
        # controller who the master is now.
        self.master = False
        self.state = State.PASSIVE
        # The drone's epoch of our current or last mastership (0: none yet).
        self.epoch = 0
        # Our epoch before a handover message made us master: ours again if the
        # ring shows that role was handed on before we took it (``_handle``).
        self._epoch_before_handover = 0
        # The log number of the handover message that made us master last (0: none).
        self._made_master_at = 0
        # The epoch of the drone's last Connected event: a controller made ACTIVE by
        # a handover message has not heard from the drone in its epoch yet.
        self.granted_epoch = 0
        # The highest log number the predecessor said it holds (its stream's
        # sync frame); None until it has said. A controller the drone grants
        # the role goes ACTIVE only once it has handled that much, so that a
        # restarted one never writes over log numbers the ring already used.
        self.catch_up_to: int | None = 0 if len(ring) == 1 else None
        # The sync frames' words above what we handled: log number -> the epoch of
        # the sender's message with it (0 if unknown). A word of a framing older
        # than a message we handled is not the ring's log, and is taken back
        # (``_take_back_stale_words``).
        self._promised: dict[int, int] = {}
        # Bounds on the epochs (non-zero) of the queued messages: the oldest is at
        # least the first, the newest at most the second (both 0 when none was
        # queued since the queue was last empty). They spare a look at every queued
        # message on every message received (``_queue``).
        self._queued_epochs = (0, 0)
        # A taker's second condition: the drone's watermark at the takeover.
        self.must_hold_reqnr = 0
        # The epoch of a mastership of ours whose log is the ring's now (0: none): we
        # handed it over cooperatively, or the ring went on without us acting in it.
        self._mastership_over = 0
        # The epoch of our takeover grant (0: none), while it is our mastership.
        self._took_over_in = 0
        # The epoch we last went ACTIVE in and the log number we held then: our own
        # messages of that mastership follow it (``framed_after``).
        self._active_from: tuple[int, int] = (0, 0)
        # Log numbers received over the ring, so that a message re-sent after a
        # reconnect is neither forwarded nor handled twice.
        self._received = SeenNumbers()
        self.replayed = 0
        self.invoked = 0
        # The replication watermark (docs/design.md, "Takeover"): the highest
        # request number every reachable controller holds. The predecessor
        # holding log number L means every controller from us round to it
        # holds L; ``_ends`` maps the log numbers above the watermark to the
        # request number held once each is, so the predecessor's word
        # becomes a request number. The master sends it on every Invoke.
        self.held_reqnr = 0  # the highest request number this controller holds
        # The epoch of each recent log number handled or created (for Diverged).
        self._epoch_at: dict[int, int] = {}
        # The framing of each recent request held: the epoch of the message (or of
        # our mastership) it was logged in, that message's log number (0: in our
        # log, not flushed yet), and what the program saw (``replaced_framing``).
        self._framed: dict[int, tuple[int, int, tuple[bytes, int, bool, bytes]]] = {}
        # A framing a later mastership replaced, from this log number on, in this
        # epoch or an older one: refused (``refuse_replaced``; None: none).
        self._replaced_from: tuple[int, int] | None = None
        self.watermark_reqnr = 0
        self._ends: deque[tuple[int, int]] = deque()
        # The highest log number we held that the predecessor's word says every
        # controller held (the watermark's log number): ``kept_when_fenced``.
        self.acked_lognr = 0
        # The watermark the drone took from us as master (a call that carried it, or
        # more, answered: ``drone_took_watermark``), and the highest log number whose
        # requests are all at or below it; the (log number, request number) pairs the
        # watermark passed that it has not reached yet.
        self.told_watermark = 0
        self.told_lognr = 0
        self._passed: deque[tuple[int, int]] = deque()
        # The drone's watermark at the takeover that fenced us (on_fenced; 0: not said).
        self._fenced_watermark = 0
        # Our log messages, every one up to this, that the taker which fenced us built
        # its own on (on_fenced: it held the last of them, of the same epoch).
        self._taker_built_on = 0
        # Our program starts again by a rejoin (``restart_program``): like fenced,
        # nothing queued is handled here any more (the fresh self handles it); and
        # the log number up to which it keeps its history for its fresh self.
        self.restarting = False
        self._restart_keeps = 0
        # The last handover message we created, until it comes back round: if
        # its new master is lost and the drone gives the role back to us by
        # takeover, we are the only one that holds it (``_resend_handed``).
        self._handed: ring_pb2.LogMessage | None = None
        # The epoch of the last mastership we flushed a log message in (0: none):
        # ``mastership_given_up``.
        self._flushed_in = 0
        # The epoch of a mastership whose log an earlier self of this process gave
        # up when it rejoined (0: none): ConnectRequest.given_up_epoch, set by the
        # runtime on the fresh self (``mastership_given_up``).
        self.given_up_epoch = 0
        # The newest word of an ACTIVE master the ring gave us: its epoch, and the
        # log number it held then (``on_sync``, ``master_word``); (0, 0): none.
        self._master_word = (0, 0)
        # On a signed ring, that word as its master signed it (``on_sync``), and ours
        # since we went ACTIVE (``master_proof``); None: none.
        self._master_proof: ring_pb2.MasterWord | None = None
        self._own_word: ring_pb2.MasterWord | None = None
        # On a signed ring, the proof of holding each of our own messages above the
        # watermark that went to our successor only (``holding_proof``): a word that a
        # controller holds one moves the watermark only with it (``_on_holds``).
        self._proofs: dict[int, bytes] = {}
        # The drone's grants of the masterships we hold or held, by epoch (from
        # Connected, or the handover message that made us master): every message
        # we create carries the grant of the mastership it claims (``_backed``).
        self._grants: dict[int, drone_pb2.Grant] = {}

    # -- lines 1-11 -------------------------------------------------------------

    def start(self) -> list[Effect]:
        """Initialization: every controller asks the drone whether it is the master.

        Line 7 has the initial master connect; here the drone's answer decides
        (``on_granted``), so a controller restarted mid-mission does not take
        the role from its configuration.
        """
        return [ConnectDrone()]

    # -- the drone's word ---------------------------------------------------------

    def on_granted(
        self,
        epoch: int,
        takeover: bool = False,
        watermark_reqnr: int = 0,
        grant: drone_pb2.Grant | None = None,
    ) -> list[Effect]:
        """The drone's Connected event: this controller is master in ``epoch``.

        After a handover (Algorithm 1) the controller is ACTIVE already and
        learns its epoch. Otherwise it was not made master by the log: the
        mission's start, a restart while the drone held it as master, or a
        takeover. It becomes ACTIVE once caught up (``_drain``): with the
        ring, or, in a takeover, with what it holds (its predecessor may be
        the lost master; the drone gave it every reply above the watermark,
        and the taker, first after the lost master, holds every message that
        left it). A taker that holds less than the drone's
        ``watermark_reqnr`` (it restarted or rejoined with nothing: the drone
        let go of the replies the others hold) waits until the ring gave it
        that much. ``grant``: the drone's signed word of it, which our messages of
        that epoch carry.
        """
        if grant is not None:
            self._grants[epoch] = grant
        self.epoch = self.granted_epoch = epoch
        if self.state is State.ACTIVE:
            self._owed_epoch = 0  # ACTIVE already: whatever was owed came, or is moot
            return []
        self.master = True
        effects: list[Effect] = []
        # A cooperative grant (not the first master's, not a takeover) comes with
        # a handover message of its epoch, sent directly by the old master: it
        # carries the old master's log, so we wait for it (ACTIVE without it, we
        # would reuse its log number or re-send requests it served). If the old
        # master died before it left, the drone grants us again by takeover.
        self._owed_epoch = 0 if takeover or epoch <= 1 else epoch
        if takeover:
            effects.extend(self._resend_handed())
            # What the predecessor said it holds may never come (it may have
            # died with it); the drone has every reply above what we hold.
            self.catch_up_to = self.holds_lognr
            self.must_hold_reqnr = watermark_reqnr
            self._took_over_in = epoch
        return effects + self._drain()

    def _resend_handed(self) -> list[Effect]:
        """Our own handover message, sent only to a new master the drone has lost, as a
        normal message of ours to the ring.

        A taker that handed over last and has handled nothing since holds
        the log up to that message, which may never have left it (its new
        master died with it). It goes on numbering after it, so the ring
        must get it: we send it on as its new master would have, a normal
        message, here with us as origin. If it did leave, the copies have
        the same number, epoch and entries, and the second is a duplicate.
        """
        handed, self._handed = self._handed, None
        if handed is None or handed.lognr != self.lognr or handed.lognr in self._received:
            return []
        self._received.add(handed.lognr)
        message = ring_pb2.LogMessage()
        message.CopyFrom(handed)
        message.handover = False
        message.origin = message.sender = self.id
        return [SendLog(self.successor, message)]

    def on_sync(
        self,
        holds_lognr: int,
        holds_epoch: int = 0,
        master_epoch: int = 0,
        master_lognr: int = 0,
        holds_proof: bytes = b"",
        master_proof: ring_pb2.MasterWord | None = None,
        holds_backed: bool = True,
    ) -> list[Effect]:
        """A sync frame: the sender's word on what it holds (``_on_holds``), and on the
        newest ACTIVE master it knows of (``master_epoch``, ``master_lognr``: 0 for none).

        Masters number log messages in the order of their epochs, and a master
        ACTIVE in ``master_epoch`` holding ``master_lognr`` creates every number
        above it in that epoch or a newer one: a queued message numbered above
        it of an older epoch is not the ring's, and is dropped (``Unqueued``).
        A message of the master's would drop it too, but a master may have
        nothing more to log (a fresh self granted a newer epoch after its
        earlier self flushed on a framing it gave up): without the word, every
        controller would hold that stale message queued above the ring's top
        for ever. The newest word is said on again in our own sync frames
        (``master_word``), with its master's signed word on a signed ring
        (``master_proof``; the driver's core believes a word only with it,
        ``ControllerCore.sync_arrived``). ``holds_proof`` and ``holds_backed``:
        ``_on_holds``.
        """
        effects: list[Effect] = []
        if master_epoch > 0:
            newest, at = self._master_word
            if master_epoch > newest or (master_epoch == newest and master_lognr < at):
                self._master_word = (master_epoch, master_lognr)
                self._master_proof = master_proof
            effects = self._drop_stale_queued(master_lognr, master_epoch)
        return effects + self._on_holds(holds_lognr, holds_epoch, holds_proof, holds_backed)

    @property
    def master_word(self) -> tuple[int, int]:
        """What our sync frames say of the newest ACTIVE master we know of: its epoch and
        the log number it held ((0, 0): none). Our own while ACTIVE, else the newest
        word the ring gave us (``on_sync``)."""
        if self.state is State.ACTIVE:
            return self.epoch, self.lognr
        return self._master_word

    @property
    def heard_master_word(self) -> tuple[int, int]:
        """The newest master word the ring gave us (``on_sync``), ours aside."""
        return self._master_word

    @property
    def master_proof(self) -> ring_pb2.MasterWord | None:
        """On a signed ring, the master's signed word our sync frames carry with
        ``master_word`` (None: none, or an insecure ring): ours while ACTIVE, signed
        when we went ACTIVE (every message above its log number is ours or newer, so
        it holds for the whole mastership), else the one the ring gave us."""
        if self.state is State.ACTIVE:
            return self._own_word
        return self._master_proof

    def _went_active(self) -> None:
        """We go ACTIVE: on a signed ring, our word as master is signed once, with the
        drone's grant of the epoch (``master_proof``)."""
        self.state = State.ACTIVE
        self._own_word = None
        if self._active_from[0] != self.epoch:
            self._active_from = (self.epoch, self.lognr)
        if self.seal is _unsealed:
            return
        word = ring_pb2.MasterWord(epoch=self.epoch, lognr=self.lognr, master=self.id)
        grant = self._grants.get(self.epoch)
        if grant is not None:
            word.grant.CopyFrom(grant)
        self.seal(word)
        self._own_word = word

    @property
    def framed_after(self) -> tuple[int, int] | None:
        """In an ACTIVE mastership granted by takeover, the log message our own messages
        follow, (lognr, epoch) (None otherwise): what we held when we went ACTIVE
        (``(0, 0)``: nothing). Above it, the
        ring's log is ours, in our epoch, or newer: messages of an older epoch that
        come after are fenced (``_arrival``). Our drone calls say it
        (``InvokeRequest.framed_after_lognr``), so that the drone can refuse a later
        taker that holds another framing of those numbers."""
        epoch, lognr = self._active_from
        if self.state is not State.ACTIVE or epoch != self.epoch:
            return None
        if self._took_over_in != self.epoch:
            return None
        return lognr, self.epoch_of(lognr) if lognr else 0

    def mastership_given_up(self) -> int:
        """The epoch of a mastership of ours whose log a rejoin now gives up (0: none), for
        the fresh self to tell the drone (``given_up_epoch``, ConnectRequest).

        A master that flushed log messages in its epoch and rejoins with nothing
        (its log diverged from the ring's, or a taker's framing was replaced)
        leaves those messages on the ring. Granted the same epoch again, its
        fresh self would number messages like them in the same epoch, which no
        rule tells apart (a duplicate by number), and nothing newer would
        replace them where they are queued. The
        drone grants it a new epoch instead, by a takeover of its earlier self
        (``Sequencer.take_over_from_earlier_self``). Not a fenced controller
        (the role went to another), nor one whose program starts again (its
        log is the ring's, and kept: ``restart_program``). What an earlier
        self said is said again.
        """
        ours = self.epoch if self.master and self._flushed_in == self.epoch else 0
        if self.fenced or self.restarting:
            ours = 0
        return max(ours, self.given_up_epoch)

    def _on_holds(
        self, holds_lognr: int, holds_epoch: int, proof: bytes = b"", backed: bool = True
    ) -> list[Effect]:
        """The predecessor holds every log message up to ``holds_lognr`` and sends what we lack.

        Also moves the watermark: every controller holds what the predecessor does.
        ``holds_epoch`` is the epoch of the sender's message ``holds_lognr`` (0 if
        unknown). Masters number log messages in the order of their epochs, so a
        sender whose top message is older than one we handled, and numbered above
        it, holds another framing (one a takeover replaced, not given up yet: the
        sender will see the ring's and rejoin): its word says nothing of the
        ring's log, and a master that waited for it would wait for ever. Nor
        does a sender whose message with a number we hold is older than ours:
        it holds the framing ours replaced, not ours, and the watermark stays
        (``_replaced_word``).

        On a signed ring the word is one station's, which may lie (docs/design.md,
        "A sync frame's words, believed on evidence"): the watermark moves only up
        to a message of our own whose ``proof`` of holding came back
        (``_watermark_credit``), a message of a newer epoch than ours rejoins
        us only ``backed`` by the drone's grant of that epoch, never while ACTIVE
        (``_believes_newer``), and a promise above what we hold is waited for only
        so backed (``_believes_promise``).
        """
        ours = self._epoch_at.get(holds_lognr, 0) if 0 < holds_lognr <= self.lognr else 0
        if 0 < holds_epoch < ours:
            return self._replaced_word(holds_lognr)
        if 0 < ours < holds_epoch and not self._believes_newer(backed):
            return self._replaced_word(holds_lognr)
        if 0 < ours < holds_epoch:
            # The sender's message with that number is of a newer epoch than ours:
            # a takeover framed it anew (our framing never left a master that was
            # lost or fenced). The same-number rule of ``on_log``, for a sender
            # that holds less than we do: it gives us nothing above our hello,
            # so its message with that number would never come, and a later
            # taker holding ours would build on the replaced framing.
            return [Diverged(holds_lognr, ours, holds_epoch)]
        if holds_lognr > self.lognr and (
            0 < holds_epoch < self.epoch_of(self.lognr)
            or self._replaced_framing_of(holds_lognr, holds_epoch)
        ):
            if self.catch_up_to is None:
                self.catch_up_to = 0  # the sender holds nothing of the ring's above ours
            return self._drain()
        promise = holds_lognr if self._believes_promise(holds_epoch, backed) else self.lognr
        self.catch_up_to = max(self.catch_up_to or 0, min(holds_lognr, promise))
        if holds_lognr > self.lognr and promise == holds_lognr:
            self._promised[holds_lognr] = max(self._promised.get(holds_lognr, 0), holds_epoch)
        credit = self._watermark_credit(holds_lognr, holds_epoch, proof)
        while self._ends and self._ends[0][0] <= credit:
            acked, reqnr = self._ends.popleft()
            self.watermark_reqnr = max(self.watermark_reqnr, reqnr)
            self.acked_lognr = max(self.acked_lognr, acked)
            self._passed.append((acked, reqnr))
        self._reach_told()
        return self._drain()

    def drone_took_watermark(self, watermark: int) -> None:
        """The drone answered a call of ours that carried ``watermark`` or more: it let go
        of its replies up to it (``ReplyCache.raise_watermark``), and grants the role to
        no taker with a lower one from now on, so no taker frames a request up to it
        anew (it must hold them before it acts, ``must_hold_reqnr``)."""
        self.told_watermark = max(self.told_watermark, watermark)
        self._reach_told()

    def _reach_told(self) -> None:
        while self._passed and self._passed[0][1] <= self.told_watermark:
            self.told_lognr = max(self.told_lognr, self._passed.popleft()[0])

    def unproved_word(self, holds_lognr: int, holds_epoch: int, proof: bytes) -> bool:
        """Whether a word that its sender holds our own message ``holds_lognr`` (of the
        epoch we framed it in) came without the proof of holding it that we kept: an
        honest holder of it computes it (``_watermark_credit``), so the sender lies."""
        kept = self._proofs.get(holds_lognr)
        return kept is not None and proof != kept and holds_epoch == self.epoch_of(holds_lognr)

    def _believes_promise(self, holds_epoch: int, backed: bool) -> bool:
        """Whether a word that the sender holds messages above ours is waited for
        (``catch_up_to``: a master granted the role goes ACTIVE only once it handled
        them). On an insecure ring, yes. On a signed one only of an epoch the drone
        granted (``backed``; every message of a signed ring is of one, and carries its
        grant): a promise of an older epoch is taken back once we handle a message of
        a newer one (``_take_back_stale_words``), so a station that promises what it
        never sends holds a new master up until its handover message at most, where
        a promise of no epoch, or of one never granted, would hold it for ever."""
        if self.seal is _unsealed:
            return True
        return backed and holds_epoch > 0

    def _believes_newer(self, backed: bool) -> bool:
        """Whether a word that the sender's message with one of our numbers is of a newer
        epoch than ours counts (it rejoins us with nothing). On an insecure ring, yes. On a
        signed one only with the drone's grant of that epoch (``backed``), and not while
        ACTIVE: only the drone fences a master, and a station could claim a genuine newer
        epoch for a number below our mastership's first message."""
        if self.seal is _unsealed:
            return True
        return backed and self.state is not State.ACTIVE

    def _watermark_credit(self, holds_lognr: int, holds_epoch: int, proof: bytes) -> int:
        """The log number up to which a predecessor's word that it holds ``holds_lognr``
        (of ``holds_epoch``) moves the watermark.

        On an insecure ring, all of it. On a signed ring, only a message of our own
        whose holding ``proof`` is the one we kept when we sent it to our successor:
        an honest controller passes a message on only once it holds it whole, so
        the proof shows every controller from our successor round to the sender
        holds it (and, the links delivering in order, what we sent before it); a
        station that lies cannot make the proof of a message it does not hold, nor
        of one made by another, nor forge ours. Not one we also sent straight to a
        prepared handover's target, which holds it without the ring. A word
        without a proof that counts moves nothing: the drone retains the replies
        a little longer.
        """
        if self.seal is _unsealed:
            if holds_lognr > self.lognr and holds_epoch > self._epoch_at.get(self.lognr, 0):
                # Above our top, of a mastership newer than it: built on ours by a
                # handover, or framed anew by a takeover that never held ours, and
                # nothing tells which. Counted, a fenced master would keep as gone
                # round what the taker replaced (``kept_when_fenced``). A signed
                # ring has no proof for it either.
                return 0
            return holds_lognr
        if not proof or self._proofs.get(holds_lognr) != proof:
            return 0
        for kept in [n for n in self._proofs if n <= holds_lognr]:
            del self._proofs[kept]
        return holds_lognr

    def _replaced_word(self, holds_lognr: int) -> list[Effect]:
        """The predecessor holds message ``holds_lognr`` of an older epoch than ours: a
        framing a takeover replaced (it will see the ring's and rejoin). Caught up
        with it as far as numbers go, but the watermark does not move.

        The watermark says every controller holds our requests up to it, and the
        drone lets their replies go. Taken from such a word (a master's own
        messages of its takeover epoch, the predecessor still holding the lost
        master's), it would let the drone drop the replies of the newer framing:
        the next taker, holding the older one (a lost master's Clock reading or
        give-up), would find nothing retained to compare it with
        (``replaced_framing``) and build on it, while the drone acted for a
        program that saw the newer one: two programs shown different replies.
        """
        self.catch_up_to = max(self.catch_up_to or 0, holds_lognr)
        return self._drain()

    def _framing(self, entries: Sequence[ring_pb2.LogEntry], epoch: int, lognr: int) -> None:
        """``entries`` are held as framed in ``epoch``, in log message ``lognr`` (0: our
        log's, not flushed yet): ``replaced_framing``."""
        for entry in entries:
            self._framed[entry.reqnr] = (epoch, lognr, seen_as(entry))
        if entries and len(self._framed) > 2 * EPOCHS_KEPT:
            newest = entries[-1].reqnr
            for old in [n for n in self._framed if n <= newest - EPOCHS_KEPT]:
                del self._framed[old]

    def replaced_framing(
        self, replies: Sequence[drone_pb2.RetainedReply]
    ) -> ReplacedFraming | None:
        """The first of the replies the drone retains whose request we hold in a framing
        a later mastership replaced: brought to the drone in a newer epoch than the one
        we hold it framed in, and other than ours (None: none is).

        A taker builds on what it holds, and the ring's version of a request is
        its newest framing: the drone keeps each request as the first master
        that brought it framed it (or a give-up the program saw), and a master
        of a later epoch brings it only if it did not hold an earlier framing
        that reached the drone, so an older framing held here that differs was
        replaced by a takeover that did not hold it (a cut-off master's Clock
        reading framed again). Same content, or a
        framing of ours as new as the drone's (a give-up of a request the drone
        served, not yet sent along), is the ring's.
        """
        for kept in replies:
            framed = self._framed.get(kept.reqnr)
            if framed is None or kept.reqnr > self.held_reqnr:
                continue
            epoch, lognr, seen = framed
            if epoch < kept.epoch and seen != seen_as(kept):
                return ReplacedFraming(kept.reqnr, lognr or self.lognr + 1, epoch, kept.epoch)
        return None

    def refuse_replaced(self, replaced: ReplacedFraming) -> None:
        """From ``replaced.lognr`` on, log messages of ``replaced.ours_epoch`` or older
        are not the ring's: neither held nor forwarded, and a predecessor's word
        that it holds one does not count.

        Set on the fresh protocol of a taker that found its framing replaced
        (``replaced_framing``) and rejoined. The ring may hold nothing newer:
        the master that framed the request anew may have been lost before its
        messages left. Given the replaced framing again, the taker would find
        it replaced again, for ever. Refusing it, the
        taker holds what precedes it, is answered from the drone's retained
        replies from there (the newer framing), and its own messages (of its
        newer epoch) replace the older framing on the ring (``Diverged``).
        Only that framing and older ones: masters number log messages in the
        order of their epochs, so one of an epoch between ours and the drone's
        is another framing, which may be the drone's lineage up to the
        request; if it too holds a version the drone replaced, the taker finds
        it and refuses that one in turn, an epoch newer each time.
        """
        self._replaced_from = (replaced.lognr, replaced.ours_epoch)

    def _replaced_framing_of(self, lognr: int, epoch: int) -> bool:
        """Whether message ``lognr`` of ``epoch`` is of a refused framing (``refuse_replaced``)."""
        if self._replaced_from is None:
            return False
        from_lognr, up_to_epoch = self._replaced_from
        return lognr >= from_lognr and 0 < epoch <= up_to_epoch

    def _held(self, lognr: int, reqnr: int, epoch: int) -> None:
        """Log message ``lognr`` of ``epoch`` is held, and with it every request up to ``reqnr``."""
        self._epoch_at[lognr] = epoch
        if len(self._epoch_at) > 2 * EPOCHS_KEPT:
            for old in [n for n in self._epoch_at if n <= lognr - EPOCHS_KEPT]:
                del self._epoch_at[old]
        self.held_reqnr = max(self.held_reqnr, reqnr)
        if len(self.ring) == 1:
            self.watermark_reqnr = self.held_reqnr  # nobody else to hold it
        else:
            self._ends.append((lognr, self.held_reqnr))

    def may_route_around(
        self, skipped: list[int], routed_around: list[int], drone_connected: bool
    ) -> bool:
        """Whether the ring may skip ``skipped`` now (``ring_route``'s choice), where it
        skips ``routed_around`` already (docs/design.md, "The ring routes around the dead").

        Not an ACTIVE controller cut off from the drone, skipping one more: it
        may be lost, and the drone then makes the first controller after it
        that the drone reaches master by takeover, which must hold every
        message that left it. A successor the master cannot reach may still be
        reachable by the drone (one partition cuts the master off from both);
        routed around it, the master's last flushes (give-ups of requests that
        never reached the drone) would reach the replicas after the taker and
        not the taker, and a later taker holding them would build on a framing
        the drone replaced. Held back, they are lost
        with the master like its unflushed log. Going back towards the natural
        successor is always allowed, and so is everything once connected.
        """
        if self.state is not State.ACTIVE or drone_connected:
            return True
        return set(skipped) <= set(routed_around)

    def route_to(self, successor: int) -> None:
        """Log messages go to ``successor`` from now on: the ring routes around the
        unreachable ones between us (the runtime decides; docs/design.md)."""
        if successor == self.id or successor not in self.ring:
            raise ValueError(f"controller {self.id} cannot route the ring to {successor}")
        self.successor = successor

    @property
    def log_mastership_epoch(self) -> int:
        """The epoch of the mastership whose log we may hold alone (ConnectRequest.
        mastership_epoch, kept in the history file): the drone fences us if a
        takeover gave that log up.

        Our epoch, unless we handed that mastership over and our handover message
        came back round (or the ring went on past it), or never acted in it and
        the ring went on in a newer one (``_handle``): its log is the ring's
        then, and we hold none of a later mastership we never heard of. The
        drone would otherwise take a takeover of such a later mastership (one a
        cooperative handover gave us while we were cut off, lost before we knew)
        for one of our log, and a taker that held the ring's log would rejoin
        with nothing, leaving nobody with the requests below the watermark.
        """
        handed_back = self._handed is None and self.state is not State.ACTIVE
        if self.epoch and self._mastership_over == self.epoch and handed_back:
            return 0
        return self.epoch

    @property
    def holds_lognr(self) -> int:
        """Every log number up to this one was received (handled, or queued to be).

        Our handover message, until it comes back round, is not held: it is
        not in the history we give our successor (a history copy could
        overtake it), so a predecessor that re-sends from our hello (a stream
        re-opened, or routed back to us) must give it to us, or nobody ever
        gets its log number from us. Once
        the ring went on past it (its new master handed the role straight
        back to us, and that message overtook it), it counts as received: it
        may never come back, and our history has it once its new master
        acknowledged it (``ControllerNode._handover_acked``).
        """
        return self._received.upto

    def fresh_self(self) -> ControllerProtocol:
        """The protocol of this controller rejoining with nothing (``ControllerNode.reset``).

        It knows nothing of the log, but says which mastership its earlier self
        gave up (``given_up_epoch``, on every Connect) and remembers the takeover
        that fenced it: a handover message that gave the earlier self a role
        in an epoch that takeover ended gives the fresh self none (``_arrival``).
        """
        fresh = ControllerProtocol(self.id, self.ring, self.flush_limit)
        fresh.seal = self.seal
        fresh._grants = dict(self._grants)
        fresh.given_up_epoch = self.mastership_given_up()
        fresh._fenced_in = self._fenced_in
        return fresh

    def kept_for_rejoin(self) -> list[ring_pb2.LogMessage]:
        """The handover messages sent to us and not handled yet, for the controller that
        rejoins with nothing (``Diverged``) to receive again after its reset.

        A handover message goes from the old master to the new one only, and
        enters the old master's history only once it has come back round (a
        history copy must not overtake it): a new master that rejoins before
        handling it holds the one copy. Were it dropped with the rest, no
        controller would ever get its log number, and the new master would
        number its own messages like it. Its fresh self queues it until it has
        caught up, handles it in order, and takes the role as the drone decided.
        Not one older than a takeover that fenced us: that role is gone.
        """
        kept = [m for _, m in sorted(self.log_queue.items()) if m.handover]
        if self._diverging_handover is not None:
            kept.append(self._diverging_handover)
        # One older than the takeover that fenced us gives a role the drone took away.
        return [m for m in kept if m.epoch > self._fenced_in]

    def kept_when_fenced(self) -> int:
        """The log numbers (every one up to this) that a controller fenced by a takeover
        keeps from its history when it rejoins.

        - In any ring, those up to the message the taker built its own on, when
          we hold that message of the same epoch (``on_fenced``): a message is
          known by its number and epoch, and the taker's log is its lineage.
        - In any ring, those whose requests are all at or below the watermark
          the drone took from us as master (``told_lognr``): the drone let go of
          their replies, and every taker since must hold them before it acts, so
          none framed them anew; the fenced master may hold the only copy left
          (the others lost, or restarted or rejoined with nothing), and dropped,
          the taker would wait for ever for them.

        In a ring of two, also:

        - Those that went round the whole ring (``acked_lognr``): the drone let
          go of their replies, and the fenced master may hold the only copy
          left (the other controller restarted with nothing); dropped, the
          taker would wait for ever for them. Not the rest, which the taker
          may have framed anew.
        - The messages queued right after them framed in the fencing
          takeover's epoch or a newer one: the ring's log, of which a master
          cut off from the drone may hold the only copy (the taker handed the
          role back to it and died).
        - Not a handover message (``kept_for_rejoin`` keeps it, flag and all),
          nor anything past one: a history copy of it, fed to the fresh self
          and forwarded, would overtake it (``World.check_overtaken_handover``
          checks F7).

        In a longer ring the predecessor's word may come from a controller that
        routes around one that lacks them, which may then take over without
        them, with the drone's watermark below ours: the fenced controller would
        keep a give-up the taker replaced. Not below the watermark the drone
        took, which binds that taker too.
        The fresh self handles what is kept like ring messages
        (``ControllerNode.reset``) and gives it to its successor again.
        """
        if not self._fenced_in:
            return 0
        if len(self.ring) != 2:
            return max(self._taken_lognr(), self._taker_built_on)
        upto = self.acked_lognr
        while (queued := self.log_queue.get(upto + 1)) is not None:
            if queued.handover or queued.epoch < self._fenced_in:
                break
            upto += 1
        return max(upto, self._taken_lognr(), self._taker_built_on)

    def _taken_lognr(self) -> int:
        """The highest log number whose requests are all at or below a watermark the
        drone took: one it answered a call of ours with (``told_watermark``), or the
        one it had when it took our mastership over (``_fenced_watermark``)."""
        taken = max(self.told_watermark, self._fenced_watermark)
        passed = [lognr for lognr, reqnr in self._passed if reqnr <= taken]
        return max([self.told_lognr, *passed])

    def restart_program(self) -> list[Effect]:
        """Our program starts again by a rejoin (it gave up on a call whose entry, from
        the log or a reply the drone retains, is not a give-up: node.py
        ``_replay_again``). Nothing queued is handled here any more; a master in
        the drone's epoch flushes its log and keeps every message up to it for its
        fresh self (``kept_history``), and a replica keeps what it handled.

        A rejoin drops everything, as for a replica whose log diverged; but only
        the program went astray here, not the log. A master's log is the ring's
        (it frames the drone's replies in the drone's epoch), and so is what a
        replica handled (from the ring, as far as it knows: a framing the drone
        replaced is found again by the fresh self, ``Diverged``), up to the
        handover message that made it master, if one did: the fresh self must take
        that one again, flag and all. Either may be
        the only copy left (the other controllers lost or restarted with nothing,
        the replies below the watermark let go by the drone): dropped, a taker
        would wait for ever for requests nobody holds. A master ACTIVE in an epoch
        the drone has not granted it keeps nothing: what it logged past the ring
        may be a framing a takeover replaced. And until the rejoin the controller handles
        nothing queued: a handover message that made it master would otherwise
        be neither queued (``kept_for_rejoin``) nor anywhere else with its
        flag, the fresh self given the old master's history copy would be no
        master, and the drone, which had moved the role on from it already,
        would wait for ever for its handover.
        """
        self.restarting = True
        if self.state is not State.ACTIVE:
            # Not past a handover message that made us master (F7, ``kept_history``).
            made = self._made_master_at if self.master else 0
            self._restart_keeps = made - 1 if made else self.lognr
            return []
        if self.granted_epoch != self.epoch:
            return []
        effects = self._flush_to_all() if self.log else []
        self._restart_keeps = self.lognr
        return effects

    def kept_history(self) -> int:
        """The log numbers (every one up to this) a controller that rejoins keeps from its
        history for its fresh self: a master's whose program starts again
        (``restart_program``) unless fenced since, and what ``kept_when_fenced``
        keeps. Nothing from a handover message the fresh self is given
        (``kept_for_rejoin``) on: a history copy of it, handled first, would take its
        number without its flag, and the role it gives would be lost (F7)."""
        restarted = 0 if self.fenced else self._restart_keeps
        upto = max(restarted, self.kept_when_fenced())
        handed = [m.lognr for m in self.kept_for_rejoin()]
        return min([upto, *(lognr - 1 for lognr in handed)])

    def handover_settled(self, lognr: int) -> bool:
        """Whether our handover message ``lognr`` no longer gives its receiver the role.

        It came back round, the ring went on past it (its new master handled
        it: only the master creates the numbers after it), or we sent it on
        ourselves as a taker (``_resend_handed``). A copy still unacknowledged
        on the direct stream is then sent without the flag: a new master
        restarted with nothing after it handed the role on would take it again,
        ACTIVE in an epoch long over.
        """
        return lognr in self._received

    @property
    def mastership(self) -> Mastership:
        """Our masterships as one value, whose legal combinations ``Mastership.problems``
        states."""
        return Mastership(
            state=self.state,
            master=self.master,
            epoch=self.epoch,
            granted=self.granted_epoch,
            took_over_in=self._took_over_in,
            owed=self._owed_epoch,
            over=self._mastership_over,
            flushed_in=self._flushed_in,
            fenced=self.fenced,
            fenced_in=self._fenced_in,
            before_handover=self._epoch_before_handover,
        )

    def epoch_of(self, lognr: int) -> int:
        """The epoch of the message with ``lognr`` handled or queued here (0 if unknown):
        what the ring hello says with ``holds_lognr`` (``resend_after``)."""
        queued = self.log_queue.get(lognr)
        if queued is not None:
            return queued.epoch
        return self._epoch_at.get(lognr, 0)

    @property
    def missing_lognr(self) -> int | None:
        """A log number we lack and nothing will bring by itself (a gap), if any.

        - The next one to handle, while later ones are queued without it.
        - The next one, while the predecessor's sync frame says it holds it and
          nothing is queued: the ring forwards no message to its origin, so a
          controller that rejoined or restarted with nothing after it handled
          its own handover message (or created messages) is given them again
          only by a history stream that opens after its predecessor held them.
        - Our own handover message, not come back though we handled later ones:
          a gap in our history, not in our log (a successor that rejoins with
          nothing would never get that number from us).
        """
        following = self.lognr + 1
        if following in self.log_queue:
            return None
        if self.log_queue:
            return following
        promised = self.catch_up_to is not None and self.catch_up_to >= following
        if promised and self.state is not State.ACTIVE and following not in self._received:
            return following
        if self._received.upto + 1 < self.lognr:
            return self._received.upto + 1
        return None

    @property
    def caught_up(self) -> bool:
        """Handled every log message the predecessor said it holds (and, taking over,
        every request up to the drone's watermark)."""
        return (
            self.catch_up_to is not None
            and self.lognr >= self.catch_up_to
            and self.held_reqnr >= self.must_hold_reqnr
            and self._handled_epoch >= self._owed_epoch
        )

    def connect_refusal_is_stale(self, epoch: int) -> bool:
        """Whether a Connect refusal the drone made in ``epoch`` predates our mastership.

        A controller made master by a handover message knows the epoch the
        drone granted it (the message carries the notice's); a refusal from
        an earlier epoch (our start-up question answered before the switch,
        read after it) says nothing about now: connect again.
        """
        return epoch < self.epoch

    def log_given_up(self, takeover_epoch: int) -> bool:
        """Whether a drone refusal naming another master, whose newest takeover granted
        ``takeover_epoch`` (``baton-takeover-epoch``), fences us rather than asking for
        our log.

        ACTIVE in an older epoch, we hold a log that never left us: the mastership
        went on without it (a handover notice we never heard, its new master lost
        while it waited for our handover message), and the takeover framed the same
        replies from those the drone retains. Sending it as a handover message would
        put a second framing of them on the ring (a give-up of a request the drone
        had executed, say). We rejoin with nothing instead, like a
        master whose own mastership was taken over.
        """
        return self.state is State.ACTIVE and takeover_epoch > self.epoch

    def taken_back(self, epoch: int, takeover: bool, takeover_epoch: int) -> bool:
        """Whether the drone's grant of ``epoch``, its newest takeover, gives the role back
        to us with the log we hold, which no takeover replaced (``log_given_up`` does not
        apply): ACTIVE in the epoch two before it, we never sent the handover message of
        the epoch between, so that epoch's master (a cooperative grant: a takeover of our
        mastership would have fenced us first, ``Sequencer.taken_over_since``) never
        acted, waiting for it; the drone lost it and took the role back to us, and gives
        us the replies it retains above what we hold. Fenced instead, we would drop the
        only copy of our log (the others may hold none of it)."""
        return takeover and self.state is State.ACTIVE and epoch == takeover_epoch == self.epoch + 2

    def went_on_without_us(self, message: ring_pb2.LogMessage) -> bool:
        """Whether a ring message shows our mastership went on without our log.

        ACTIVE in an older epoch than another master's message: only the drone
        grants epochs, and a mastership leaves an ACTIVE controller with its log
        only by our own handover message (we are PASSIVE after it), so one that
        went on without it went by a takeover, which framed the same replies
        from those the drone retains. Our log is given up, as
        ``log_given_up`` says when the drone tells us. The drone cannot tell a
        master it can no longer reach (out of radio range, its link down for
        good): the ring can, and ``ControllerNode.on_log`` fences us on it then.
        """
        return message.origin != self.id and self.log_given_up(message.epoch)

    def went_on_in_queue(self) -> ring_pb2.LogMessage | None:
        """A queued ring message that shows our mastership went on without our log
        (``went_on_without_us``), if any: the fence of a master cut off from the drone
        once both its streams are down, whenever that comes.

        The message may come while the drone's streams still look up (a link that
        went silent, not yet found by keepalive); queued here, ACTIVE, it would
        otherwise never be looked at again, and the master would stay ACTIVE for
        ever, its program answered by itself past the drone's last request.
        """
        if self.state is not State.ACTIVE or self._queued_epochs[1] <= self.epoch:
            return None
        for queued in self.log_queue.values():
            if self.went_on_without_us(queued):
                return queued
        return None

    def judge_refusal(self, sent_epoch: int, master: int, epoch: int) -> Refusal:
        """What a drone refusal of a request sent in ``sent_epoch`` means (drone.proto).

        The drone names its master and epoch. A refusal of a request from an
        earlier ACTIVE period (a slow uplink delivered it after the role came
        back) is STALE: nothing was executed, and it says nothing about now.
        Another master in our current epoch is a handover notice. Ourselves,
        in the epoch we sent, refusing the request number: the log and the
        drone disagree. Ourselves in a newer epoch than the one we are ACTIVE
        in: the drone handed the role away and back before its notice reached
        us (it drops a notice owed to a controller that is master again), so
        nobody else acted on it: REGRANTED, connect again to learn the epoch
        (re-sending in the old one would be refused for ever).
        """
        if self.state is not State.ACTIVE or sent_epoch != self.epoch:
            return Refusal.STALE
        if master != self.id:
            return Refusal.HANDED_OVER
        if epoch > sent_epoch:
            return Refusal.REGRANTED
        return Refusal.DISAGREE

    # -- lines 12-23: invocation while ACTIVE -----------------------------------

    def on_reply(self, entry: ring_pb2.LogEntry) -> list[Effect]:
        """Logs the drone's reply to request reqnr + 1 and flushes at the limit."""
        if self.state is not State.ACTIVE:
            raise ProtocolError(f"controller {self.id} got a drone reply while {self.state.name}")
        if entry.reqnr != self.reqnr + 1:
            raise ProtocolError(f"reply for request {entry.reqnr}, expected {self.reqnr + 1}")
        self.log.append(entry)
        self.reqnr = self.held_reqnr = entry.reqnr
        self._framing([entry], self.epoch, 0)
        self.invoked += 1
        if self.log.size >= self.flush_limit or self.preparing_for is not None:
            return self._flush_to_all()
        if self.mission_over:  # no on_mission_done will come again
            return self._flush_to_all()
        return []

    # -- a prepared handover (docs/design.md, "Prepared handover") -----------------

    def on_prepare(self, target: int, epoch: int) -> list[Effect]:
        """The drone plans a handover to ``target``: what the log holds goes now, and
        from now on every entry as it comes, to the ring and straight to the target, so
        that the handover message, when the drone moves the master, holds at most the
        last reply. Ignored unless ACTIVE in ``epoch`` (the drone's word may be late)."""
        if self.state is not State.ACTIVE or epoch != self.epoch:
            return []
        if target == self.id or target not in self.ring:
            raise ProtocolError(f"prepare handover names controller {target}")
        self.preparing_for = target
        return self._flush_to_all() if self.log else []

    def end_preparation(self) -> None:
        """The preparation is over without a handover (its time ran out): flush as usual."""
        self.preparing_for = None

    def _flush_to_all(self) -> list[Effect]:
        """A flush, to the successor and to a prepared handover's target."""
        sent = self._flush()
        target = self.preparing_for
        if target is None or target == self.successor:
            return [sent]
        self._proofs.pop(sent.message.lognr, None)  # held without the ring: no proof
        return [sent, SendLog(target, sent.message, copy=True)]

    def _flush(self) -> SendLog:
        self.lognr += 1
        # Held from now on: the received-numbers watermark moves over our own
        # flushes (which never come back to us), so it stays a few numbers. A
        # handover message does come back (footnote 3) and is forwarded then.
        self._received.add(self.lognr)
        self._held(self.lognr, self.reqnr, self.epoch)
        self._flushed_in = self.epoch
        message = self._message(self.lognr, origin=self.id, handover=False)
        message.epoch = self.epoch  # the mastership it was logged in, for diagnosis
        self._backed(message, self._grants.get(self.epoch))
        statement = self.seal(message)
        if not message.signature:
            return SendLog(self.successor, message)
        proof = self._proofs[self.lognr] = proof_of(statement)
        return SendLog(self.successor, message, proof=proof)

    @staticmethod
    def _backed(message: ring_pb2.LogMessage, grant: drone_pb2.Grant | None) -> None:
        """``message`` carries the drone's grant of the mastership it claims, if we have it
        (none on an insecure ring: nobody checks)."""
        if grant is not None and grant.epoch == message.epoch:
            message.grant.CopyFrom(grant)

    def _message(self, lognr: int, origin: int, handover: bool) -> ring_pb2.LogMessage:
        entries = self.log.take()
        return ring_pb2.LogMessage(
            lognr=lognr,
            origin=origin,
            handover=handover,
            entries=entries,
            sender=self.id,
            created_at=time.time(),
            after_reqnr=self.reqnr - len(entries),
            after_epoch=self._epoch_at.get(lognr - 1, 0),
        )

    def on_mission_done(self) -> list[Effect]:
        """Flushes what the master's log still holds once its mission program has ended.

        Not in Algorithm 1, whose missions never end: without it the replicas
        would wait forever for the last entries below the flush limit. Nor
        for an entry logged later: a call the program gave up on while PASSIVE
        is settled once ACTIVE again (node.py ``_settle_after_the_end``), and
        ``on_reply`` flushes it at once.
        """
        self.mission_over = True
        if self.state is State.ACTIVE and self.log:
            return self._flush_to_all()
        return []

    # -- lines 24-29: the drone's handover notice --------------------------------

    def on_handover_notice(
        self, new_master: int, epoch: int = 0, grant: drone_pb2.Grant | None = None
    ) -> list[Effect]:
        """Hands the unflushed log to the new master directly, with the handover flag.

        A notice that arrives while a call is in flight (footnote 2) is handled
        the same way: the in-flight call's reply, if it comes later, is not
        logged here (the runtime discards it), and the new master re-sends that
        request number, which the drone answers from its reply cache.
        ``grant``: the drone's grant of ``epoch`` to the new master, which the
        handover message carries (it makes its receiver master).
        """
        if self.state is not State.ACTIVE:
            # A repeated notice (e.g. from an Invoke rejection after the stream's).
            return []
        if epoch and epoch <= self.epoch:
            # A switch before our mastership: the drone made us master again since
            # (a takeover of the controller it had moved to), and its notice of the
            # older switch came late, on the old session's stream. Handing over now
            # would leave no master (that controller was fenced by our takeover).
            return []
        if new_master == self.id or new_master not in self.ring:
            raise ProtocolError(f"handover notice names controller {new_master}")
        self.state, self.master = State.PASSIVE, False
        self.preparing_for = None
        self._proofs.clear()  # a word can only name a newer master's top from now on
        self.lognr += 1
        self._held(self.lognr, self.reqnr, epoch)
        message = self._message(self.lognr, origin=new_master, handover=True)
        message.epoch = epoch
        self._backed(message, grant)
        self.seal(message)
        self._handed = ring_pb2.LogMessage()
        self._handed.CopyFrom(message)
        self._mastership_over = self.epoch
        effects: list[Effect] = [DisconnectDrone(), SendLog(new_master, message)]
        # PASSIVE now, we look at the message queued next while we were ACTIVE: a
        # PASSIVE controller handles only what arrives, and a takeover's messages
        # queued behind our handover message's number would wait there for ever.
        # One that shows our framing diverged rejoins us now.
        following = self.log_queue.get(self.lognr + 1)
        diverged = self._diverged_before(following) if following is not None else None
        return [*effects, diverged] if diverged is not None else effects

    def on_fenced(
        self, epoch: int = 0, watermark: int = 0, taker_holds: tuple[int, int] = (0, 0)
    ) -> list[Effect]:
        """The drone gave our mastership to another controller by takeover (in ``epoch``,
        with its watermark at ``watermark``: 0 if not said; ``taker_holds``: the log
        message, (lognr, epoch), the taker built on, (0, 0) if not said).

        Not in Algorithm 1, whose masters never fail: our unflushed log is not
        wanted (the new master got those replies from the drone), so nothing
        is sent; we stop acting as master. The runtime then rejoins as a
        replica with nothing but what ``kept_when_fenced`` keeps
        (``ControllerNode.reset``).
        """
        self._fenced_watermark = max(self._fenced_watermark, watermark)
        lognr, of_epoch = taker_holds
        if 0 < lognr <= self.lognr and 0 < of_epoch == self.epoch_of(lognr):
            self._taker_built_on = max(self._taker_built_on, lognr)
        was_active = self.state is State.ACTIVE
        self.state, self.master = State.PASSIVE, False
        self.fenced = True
        self.preparing_for = None
        self._fenced_in = max(self._fenced_in, epoch)  # the takeover's (kept_for_rejoin)
        self.log.take()
        return [DisconnectDrone()] if was_active else []

    # -- lines 30-47: a log message arrives --------------------------------------

    def on_log(self, message: ring_pb2.LogMessage) -> list[Effect]:
        """Forwards on receipt, then handles the message in order or queues it.

        Differs from the pseudo-code as docs/design.md says: a message that arrives
        in order while the controller is not PASSIVE is queued (line 44 would
        drop it), and a message already seen (a re-send after a reconnect) is
        ignored whole. Messages with a log number already handled (the old
        master's own handover message coming back, footnote 3) are forwarded
        but not handled.
        """
        arrival = self._arrival(message)
        if arrival is _Arrival.DIVERGED:
            if message.handover:
                self._diverging_handover = message
            return [Diverged(message.lognr, self._epoch_at[message.lognr], message.epoch)]
        if arrival is _Arrival.FENCED:
            return [Fenced(message.lognr, message.origin, message.epoch)]
        if arrival is _Arrival.SEEN:
            return []
        if arrival is _Arrival.REPLACES_QUEUED:
            # Not handled yet: the ring's message (a takeover's framing) takes the
            # place of one it renumbered, and goes on to the successor like it.
            self._queue(message)
            effects = self._forward(message)
            effects.extend(self._drop_stale_queued(message.lognr, message.epoch))
            try:
                effects.extend(self._drain())
            except ProtocolError as exc:
                raise ProtocolError(str(exc), effects + exc.effects) from exc
            return effects
        if arrival is _Arrival.OURS_PASSED:
            # Our handover message, back after the ring went on past it: counted
            # as received then, but still to be forwarded like any message.
            self._passed_handed = 0
            return self._forward(message)
        if self._handed is not None and message.lognr >= self._handed.lognr:
            if message.lognr > self._handed.lognr:
                # The ring went on past it: it may never come back (our hello
                # counts it now, so no predecessor gives it again), and its
                # number is held like the rest (the history has it once the new
                # master acknowledged it, ControllerNode._handover_acked). If it
                # does come back, it is forwarded all the same.
                self._received.add(self._handed.lognr)
                self._passed_handed = self._handed.lognr
            self._handed = None  # it came back, or the ring went on past it
        self._received.add(message.lognr)
        effects = self._forward(message)
        if message.lognr <= self.lognr:
            return effects  # already handled (footnote 3)
        self._queue(message)
        effects.extend(self._drop_stale_queued(message.lognr, message.epoch))
        try:
            effects.extend(self._drain())
        except ProtocolError as exc:
            raise ProtocolError(str(exc), effects + exc.effects) from exc
        return effects

    def _arrival(self, message: ring_pb2.LogMessage) -> _Arrival:
        """What a log message is to us, from its head alone (its entries do not count):
        ``on_log`` acts on it, ``forward_dest`` asks it before the entries arrived."""
        if self._replaced_framing_of(message.lognr, message.epoch):
            return _Arrival.FENCED  # a framing the drone replaced (``refuse_replaced``)
        if message.handover and message.origin == self.id and 0 < message.epoch <= self._fenced_in:
            # A role the drone took away by the takeover that fenced us: a
            # predecessor re-sends it to our fresh self until acknowledged,
            # and taking it would be fenced at the Connect again and again.
            # Its number is the taker's on the ring (it never left the old master
            # but to us), and comes from there.
            return _Arrival.FENCED
        ours = self._epoch_at.get(message.lognr, 0)
        if ours and message.epoch > ours:
            # Only a takeover numbers a message like one that exists: the
            # taker did not hold ours (it never left a master that died), and
            # framed the same replies in messages of its own. The ring's is
            # the taker's; our state past that number is not.
            return _Arrival.DIVERGED
        if ours and 0 < message.epoch < ours:
            # The same number from an older epoch: the other framing, by a master
            # a takeover replaced (cut off from the drone, it flushed on, e.g. a
            # give-up). Not the ring's: neither held nor forwarded, and not our
            # handover message coming back (a history that kept it would give it
            # to a replica that catches up from us).
            return _Arrival.FENCED
        if 0 < message.epoch < self._newest_epoch_below(message.lognr):
            # Masters number log messages in the order of their epochs: one
            # numbered after a message of a newer mastership is from a master
            # the drone replaced, which went on cut off from it and took the
            # newer message for the ring's, or of a framing a takeover
            # replaced, still held by a predecessor that has not seen the
            # ring's. Not the ring's: neither
            # held nor forwarded; the ring's own comes.
            return _Arrival.FENCED
        queued = self.log_queue.get(message.lognr)
        if queued is not None and message.epoch > queued.epoch:
            return _Arrival.REPLACES_QUEUED
        if message.lognr == self._passed_handed:
            return _Arrival.OURS_PASSED
        if message.lognr in self._received:
            return _Arrival.SEEN
        if self.state is State.ACTIVE and message.lognr > self.lognr and message.epoch < self.epoch:
            # Only the master creates log numbers above its own. One of an
            # earlier epoch that comes to us while we are master is from a
            # master the drone replaced by takeover, which went on (cut off
            # from the drone) or came back: its log is not the ring's
            # (docs/design.md, "Takeover"). One of a newer epoch means we are
            # that fenced master and do not know yet: it is the ring's, and
            # the drone will tell us.
            return _Arrival.FENCED
        return _Arrival.NEW

    def holds(self, head: ring_pb2.LogMessage) -> bool:
        """Whether ``on_log`` would do nothing with a message with this head: we have
        it already (``_Arrival.SEEN``). Cut-through lets such a message's frames go
        without parsing them (``RingReceiver``)."""
        return self._arrival(head) is _Arrival.SEEN

    def forward_dest(self, head: ring_pb2.LogMessage) -> int | None:
        """The controller ``on_log`` would forward a message with this head to,
        unchanged, if it came whole now; None if it would not, or would change it
        (a handover message travels on without its flag).

        Cut-through forwarding (docs/design.md, "The ring's forwarding") asks this
        on a message's first frame and passes the frames on as they come, all but
        the last; ``on_log`` decides again when the message is whole, and only its
        ``SendLog`` lets the last frame go.
        """
        if head.handover or self._arrival(head) not in _FORWARDED:
            return None
        if head.origin in (self.id, self.successor):
            return None
        return self.successor

    def _forward(self, message: ring_pb2.LogMessage) -> list[Effect]:
        """Lines 31-33: forward (a handover message travels on as a normal one).

        One of our own messages comes to us only when a predecessor re-sends
        its history to us after our restart: it has been round already.
        """
        if message.handover or message.origin not in (self.id, self.successor):
            forwarded = ring_pb2.LogMessage()
            forwarded.CopyFrom(message)
            forwarded.handover = False
            return [SendLog(self.successor, forwarded)]
        return []

    def _take_handed_back(self) -> list[Effect]:
        """While ACTIVE, the next message queued, if it is a handover message to us of a
        newer epoch than ours, with nothing in it, following our log at once (its number
        next to ours, its requests after ours, its epoch newer than our top's): handled.

        Such a message is the drone taking our mastership over and its taker handing
        it back before we heard of either, with nothing framed in between: the ring
        takes it as our log's next number, so queued for ever it would make our own
        message numbered like it one seen. Handled, it makes us master in its epoch,
        as it makes a PASSIVE controller (``_handle``); the drone's word of the
        takeover between, if it comes later, is older than that mastership
        (``ControllerCore.fenced``). One with entries, or not next, is a mastership
        that went on without us, which fences us (``went_on_without_us``)."""
        queued = self.log_queue.get(self.lognr + 1)
        if (
            queued is None
            or not queued.handover
            or queued.origin != self.id
            or queued.epoch <= self.epoch
            or queued.entries
            or queued.after_reqnr != self.reqnr
        ):
            return []
        diverged = self._diverged_before(queued)
        if diverged is not None:
            # It hands back a role that went on in another framing of our requests:
            # a takeover between replaced ours, and the ring's is the taker's.
            return [diverged]
        del self.log_queue[queued.lognr]
        self._master_by_handover_in(queued.epoch)
        if queued.HasField("grant"):
            self._grants[queued.epoch] = queued.grant
        return self._take_in(queued)

    def _master_by_handover_in(self, epoch: int) -> None:
        """A handover message of ``epoch``, newer than ours, makes us master in it. A
        grant's handover message is owed no more (``Mastership`` rule 4): it is numbered
        below this one, so it was handled, or its mastership was handed on without us."""
        self.epoch, self._owed_epoch = epoch, 0

    def _take_in(self, message: ring_pb2.LogMessage) -> list[Effect]:
        """Message ``message``, next in order, is handled: held (its entries already in
        our log, if any), with its number and epoch; queued messages it outdates go."""
        self.lognr = message.lognr
        self._framing(message.entries, message.epoch, message.lognr)
        self._handled_epoch = max(self._handled_epoch, message.epoch)
        self._held(
            message.lognr, message.entries[-1].reqnr if message.entries else 0, message.epoch
        )
        return self._drop_stale_queued(message.lognr, message.epoch)

    def _drain(self) -> list[Effect]:
        """Handles queued messages while PASSIVE and the next one is there (lines 34-43, 57-59).

        Not once fenced: what we hold is given up, and a message queued while we
        were ACTIVE (the taker's framing, from the ring) does not follow our log
        (handled, it would fail as starting at a request we do not expect). The
        fresh self handles it.
        Nor once our program starts again by a rejoin (``restart_program``)."""
        effects: list[Effect] = []
        if self.fenced or self.restarting:
            return effects
        if self.state is State.ACTIVE:
            effects.extend(self._take_handed_back())
        while self.state is State.PASSIVE and (self.lognr + 1) in self.log_queue:
            diverged = self._diverged_before(self.log_queue[self.lognr + 1])
            if diverged is not None:
                return [*effects, diverged]
            effects.extend(self._handle(self.log_queue.pop(self.lognr + 1)))
        effects.extend(self._drop_unfollowing_queued())
        if self.state is State.PASSIVE and self.master and not self.log_queue and self.caught_up:
            # The master's own log ran out with nothing queued: lines 54-56.
            self._went_active()
            effects.append(ConnectDrone())
        return effects

    def give_up_gap(self) -> list[Effect]:
        """A taker, caught up, whose queued messages wait for a number that the gap
        repair did not bring (``ControllerCore.gap_due``, once it had the
        predecessors re-send and the gap stayed): they are dropped (``Unqueued``),
        and it goes ACTIVE on what it holds.

        The ring's log after a takeover is what the taker holds in order, and the
        replies the drone retains above it. Messages of the lost master queued
        above a gap (the one before them died with it) are a framing the taker
        replaces with its own from those replies; kept, they would hold it
        PASSIVE for ever. Only a taker's, in its epoch, and only older messages:
        a controller's that arrive later are fenced by the taker's newer ones
        (``on_log``). Not at once: a message on its way (a partition, a
        reordering link) framed replies the programs may have seen already,
        Clock calls answered by its master among them.

        A predecessor's word that it holds messages of an older epoch than ours
        above what we hold is a word about that same framing (``_promised``):
        it is taken back with them, or a word its sender cannot keep any more
        (it was fenced and rejoined with nothing) would keep us from being
        caught up for ever. The drone's watermark still binds
        (``must_hold_reqnr``).
        """
        taker = self.state is State.PASSIVE and self.master and self._took_over_in == self.epoch
        if not taker or not self.log_queue:
            return []
        self._take_back_stale_words(self.epoch)
        if not self.caught_up:
            return []
        if (self.lognr + 1) in self.log_queue:
            return []
        effects = self._unqueue(lambda _, queued: queued.epoch < self.epoch)
        return effects + self._drain() if effects else []

    def _diverged_before(self, message: ring_pb2.LogMessage) -> Diverged | None:
        """Whether the next message in order, from a newer epoch than our last one, does
        not continue our requests: our last message is one a takeover renumbered.

        The same-number rule (``on_log``) sees that only when the ring's message with
        our last number comes to us; it may come later than the next one (a direct
        handover message, or a queue drained after a catch-up), or never (we were
        given only what lies above our hello). A message that does not start at our
        next request is never right; from an older epoch it stays the loud error of
        ``_handle``, from a newer one it is the ring's word against a framing that
        never left a lost or fenced master: we rejoin with nothing.
        """
        ours = self._epoch_at.get(self.lognr, 0)
        if self.lognr > 0 and 0 < ours < message.after_epoch:
            # Its creator's message with our last number is of a newer epoch: another
            # framing, which a takeover made of the replies ours holds, even if it
            # ends at the same request (a fenced master's give-up of a request the
            # drone executed for the taker).
            return Diverged(self.lognr, ours, message.after_epoch)
        if message.HasField("after_reqnr"):
            # Also on a message without entries: a new master's handover message
            # that continues a framing other than ours.
            start = message.after_reqnr + 1
        elif message.entries:
            start = message.entries[0].reqnr
        else:
            return None
        if start != self.reqnr + 1 and self.lognr > 0 and message.epoch > ours:
            return Diverged(self.lognr, ours, message.epoch)
        return None

    def _queue(self, message: ring_pb2.LogMessage) -> None:
        """Queues ``message`` (logQ), keeping the bounds on the queued epochs."""
        if not self.log_queue:
            self._queued_epochs = (0, 0)
        self.log_queue[message.lognr] = message
        if message.epoch:
            oldest, newest = self._queued_epochs
            oldest = min(oldest, message.epoch) if oldest else message.epoch
            self._queued_epochs = (oldest, max(newest, message.epoch))

    def _newest_epoch_below(self, lognr: int) -> int:
        """The newest epoch of a message we handled or queued numbered below ``lognr``
        (the one before it, and above what we handled, our top and the queue's)."""
        newest = self.epoch_of(lognr - 1)
        if lognr > self.lognr:
            newest = max(newest, self._epoch_at.get(self.lognr, 0))
            if self.log_queue and self._queued_epochs[1] > newest:
                for queued_nr, queued in self.log_queue.items():
                    if queued_nr < lognr:
                        newest = max(newest, queued.epoch)
        return newest

    def _drop_stale_queued(self, lognr: int, epoch: int) -> list[Effect]:
        """Drops the queued messages numbered above ``lognr`` of a mastership older than
        ``epoch``: the on_log rule for a message that came before the newer one below it
        (a framing a takeover replaced, queued while we held nothing). Their
        numbers are no longer received: the ring's messages with them must be taken."""
        oldest = self._queued_epochs[0]
        if not self.log_queue or not oldest or epoch <= oldest:
            return []
        return self._unqueue(lambda nr, queued: nr > lognr and 0 < queued.epoch < epoch)

    def _drop_unfollowing_queued(self) -> list[Effect]:
        """Drops the queued messages that follow fewer requests than our log holds: within
        one lineage a message numbered above ours follows every request ours holds
        (``after_reqnr``), so one that follows fewer is of a framing that left ours
        before (the same replies numbered otherwise by a takeover's taker), and the
        message between ours and it exists only in that framing: kept, it would stand
        for a gap no predecessor can fill. Its number is the ring's to give again.

        Not while ACTIVE: a master's count includes what it logged and has not
        flushed, and a newer mastership queued above its log fences it
        (``went_on_without_us``)."""
        if self.state is State.ACTIVE or not self.log_queue:
            return []
        held = self.held_reqnr
        return self._unqueue(
            lambda nr, queued: (
                nr > self.lognr and queued.HasField("after_reqnr") and queued.after_reqnr < held
            )
        )

    def _unqueue(self, dropped: Callable[[int, ring_pb2.LogMessage], bool]) -> list[Effect]:
        """Drops the queued messages ``dropped`` picks (``Unqueued``): their numbers are no
        longer received, so the ring's messages with them are taken."""
        picked = sorted(nr for nr, queued in self.log_queue.items() if dropped(nr, queued))
        if not picked:
            return []  # the bounds below are gates only: stale ones cost a look, no more
        effects: list[Effect] = []
        for queued_nr in picked:
            queued = self.log_queue.pop(queued_nr)
            self._received.discard(queued_nr)
            effects.append(Unqueued(queued_nr, queued.origin, queued.epoch))
        epochs = [queued.epoch for queued in self.log_queue.values() if queued.epoch]
        self._queued_epochs = (min(epochs), max(epochs)) if epochs else (0, 0)
        return effects

    def _take_back_stale_words(self, epoch: int) -> None:
        """Handled a message of ``epoch``: a sync frame's word above it from an older
        framing is not the ring's (``on_sync``), and is taken back; what is owed is
        what the other words say, or what we hold."""
        for promised in [n for n in self._promised if n <= self.lognr]:
            del self._promised[promised]  # kept
        stale = [n for n, e in self._promised.items() if 0 < e < epoch]
        if not stale or self.catch_up_to is None:
            return
        for promised in stale:
            del self._promised[promised]
        self.catch_up_to = max([self.lognr, *self._promised])

    def _handle(self, message: ring_pb2.LogMessage) -> list[Effect]:
        """Lines 35-43 for an in-order message on a PASSIVE controller."""
        self.lognr = message.lognr
        if message.entries and message.entries[0].reqnr != self.reqnr + 1:
            raise ProtocolError(
                f"log message {message.lognr} starts at request {message.entries[0].reqnr}, "
                f"controller {self.id} expects {self.reqnr + 1}"
            )
        for entry in message.entries:
            self.log.append(entry)
        effects = self._take_in(message)
        self._take_back_stale_words(message.epoch)
        if (
            self.master
            and self.state is not State.ACTIVE
            and 0 < self.epoch < message.epoch
            and self.granted_epoch < message.epoch
        ):
            # A handover message made us master in ``self.epoch``, and the ring went
            # on past it in a newer mastership: ours was handed on (or taken over)
            # already, by an earlier incarnation of ours that handled the message
            # and died before acknowledging it, so that its old master sent it to
            # us again, flag set. Masters number log messages in the order of
            # their epochs: that role is not ours to take, nor the log of that
            # mastership ours (our Connect would be fenced for a takeover of a
            # role we never took). Made master by the drone's grant instead (a
            # cooperative one whose handover message never came), that epoch is
            # ours and over: we never acted in it. Owed nothing either way.
            self.master = False
            if self.granted_epoch < self.epoch:
                self.epoch = max(self._epoch_before_handover, self.granted_epoch)
            else:
                self._mastership_over = self.epoch
            self._owed_epoch = 0
        if message.handover:
            if message.HasField("grant"):
                self._grants[message.epoch] = message.grant
            if not self.master:
                self._epoch_before_handover = self.epoch
            self.master = True
            self._made_master_at = message.lognr
            if message.epoch > self.epoch:
                self._master_by_handover_in(message.epoch)
            effects.append(TookOver(message.sender, message.lognr, self.reqnr, message.ByteSize()))
        elif self.master and self.granted_epoch < self.epoch < message.epoch:
            # Made master by a handover message the drone never confirmed, and the
            # ring's log goes on in a newer mastership than it: the role went on
            # without us (we handed it over, or a takeover gave our log up). Not
            # master: ACTIVE on it, the drone would fence us, and a fresh self
            # given the same handover message again (a stream that breaks before
            # its acknowledgement re-sends it) would take it again, for ever.
            # We never acted in that mastership: the log
            # we hold is the ring's (``log_mastership_epoch``).
            self.master = False
            self._mastership_over = self.epoch
        if self.log:
            self.state = State.REPLAY
        return effects

    # -- lines 48-63: invocation while REPLAY ------------------------------------

    def replay(self, method: str, request: bytes) -> tuple[ring_pb2.LogEntry, list[Effect]]:
        """The logged reply to the mission program's next call, without drone contact.

        Raises NonDeterminismError if the program asks for something else than
        the logged request.
        """
        if self.state is not State.REPLAY:
            raise ProtocolError(f"replay while {self.state.name}")
        entry = self.log.entries[0]
        if entry.request_digest != request_digest(method, request):
            raise NonDeterminismError(entry.reqnr, entry, method, request)
        self.log.pop_first()
        self.reqnr = entry.reqnr
        self.replayed += 1
        effects: list[Effect] = []
        if not self.log:
            # End of the replayed log: lines 51-60.
            self.state = State.PASSIVE
            effects.extend(self._drain())
        return entry, effects

    # -- observation --------------------------------------------------------------
