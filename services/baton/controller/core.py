"""The controller's decisions about its drone session, as a pure object: events in,
effects out.

``ControllerProtocol`` is Algorithm 1 and the ring; this core holds it and adds
what a controller decides about the drone's word: a grant (Connected), the
replies the drone retains for a taker, a TakeOver on the standby stream, a
refused Connect, a handover notice, being fenced by a takeover. No asyncio, no
gRPC, no clock: the controller runtime (``node.py``) and the simulation's
controller (``baton.sim.controller``) both feed it events and carry out the
effects it returns, in order, so the simulation runs the decisions that ship.

The rules (docs/design.md, "Takeover", "Epochs" and "Restarts"):

- Granted while ACTIVE in a mastership a newer takeover replaced: the role
  went on without our log; we rejoin with nothing before taking the grant.
- A grant is a takeover's when the drone says so or its epoch is the one a
  TakeOver told us: the master must then hold every request up to the
  drone's watermark before it goes ACTIVE, and answers its program from the
  replies the drone retains above what it holds.
- Retained replies that show we hold a request in a framing a later takeover
  replaced make us rejoin, refusing that framing from then on.
- Fenced (a takeover of our mastership, told by a refusal, a notice, or the
  ring while the drone is out of reach): stop acting as master, drop the
  unflushed log, rejoin as a replica with nothing. Once: a rejoin under way
  is not started again.
- A handover notice of a switch before our mastership (a takeover made us
  master since) is stale: nothing is handed over, nothing is sent.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import grpc

from baton.authenticity import Keys, holding_proof, refusal, reply_hashes
from baton.config import GAP_REPAIR_MAX_S, gap_repair_s
from baton.controller.link_core import SyncWord
from baton.controller.protocol import (
    ControllerProtocol,
    DisconnectDrone,
    Diverged,
    Effect,
    Fenced,
    NonDeterminismError,
    ProtocolError,
    Refusal,
    ReplacedFraming,
    SendLog,
    State,
    ring_route,
)
from baton.controller.sync_words import believe
from baton.digest import request_digest
from baton.drone.invariants import InvariantBroken, checking
from baton.drone.safety import sleep_refusal
from baton.rpc.errors import StatusError
from baton.rpc.methods import path, service_prefix
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2, ring_pb2

CLOCK_SERVICE = service_prefix("Clock")
CLOCK_SLEEP = path("Clock.Sleep")
CLOCK_NOW = path("Clock.Now")


def given_up_entry(
    reqnr: int, method: str, request: bytes, code: grpc.StatusCode
) -> ring_pb2.LogEntry:
    """The log entry of a call the mission program gave up on: the status it saw."""
    return ring_pb2.LogEntry(
        reqnr=reqnr,
        method=method,
        request_digest=request_digest(method, request),
        request=request,
        status_code=code.value[0],
        status_message=f"{method}: the mission program gave up on the call ({code.name}); "
        "the drone may have executed it",
        given_up=True,
    )


def to_retained(entry: ring_pb2.LogEntry) -> drone_pb2.RetainedReply:
    """A call answered without the drone (a Clock call, a call given up) as the drone
    keeps it: sent along with the next Invoke."""
    return drone_pb2.RetainedReply(
        reqnr=entry.reqnr,
        method=entry.method,
        request_digest=entry.request_digest,
        reply=entry.reply,
        status_code=entry.status_code,
        status_message=entry.status_message,
        given_up=entry.given_up,
    )


def from_retained(kept: drone_pb2.RetainedReply, method: str, request: bytes) -> ring_pb2.LogEntry:
    """A taker's log entry for its program's call, from the reply the drone retained.

    FAILED_PRECONDITION if the program asks another call than the one the
    drone served (the digests differ): the mission program diverged, as the
    drone would have refused it had the request been sent again.
    """
    digest = request_digest(method, request)
    if kept.request_digest != digest:
        raise StatusError(
            grpc.StatusCode.FAILED_PRECONDITION,
            f"request {kept.reqnr} was served to the lost master as {kept.method} (digest "
            f"{kept.request_digest.hex()[:16]}) but this mission program asks {method} "
            f"(digest {digest.hex()[:16]}): the mission program diverged",
        )
    return ring_pb2.LogEntry(
        reqnr=kept.reqnr,
        method=method,
        reply=kept.reply,
        request_digest=digest,
        request=request,
        status_code=kept.status_code,
        status_message=kept.status_message,
        given_up=kept.given_up,
        drone_epoch=kept.epoch if kept.signature else 0,
        drone_signature=kept.signature,
    )


@dataclass(frozen=True)
class DroneRefusal:
    """Where the drone stands when it refuses a request or a Connect: its trailing metadata."""

    master: int
    epoch: int
    after_reqnr: int
    # The refused controller's mastership was taken over (``baton-takeover``).
    taken_over: bool = False
    # The epoch the drone's newest takeover granted (``baton-takeover-epoch``; 0: none).
    takeover_epoch: int = 0
    # The drone's grant of ``epoch`` to ``master`` (``baton-grant``; None: not said).
    grant: drone_pb2.Grant | None = None
    # The drone's watermark at the takeover of the refused controller's mastership
    # (``baton-takeover-watermark``; 0: not said).
    takeover_watermark: int = 0
    # The log message that takeover's taker built on, (lognr, epoch)
    # (``baton-takeover-holds``; (0, 0): not said).
    taker_holds: tuple[int, int] = (0, 0)

    @classmethod
    def from_metadata(cls, metadata: Mapping[str, str | bytes]) -> DroneRefusal | None:
        """The refusal a FAILED_PRECONDITION's trailing metadata states (None: it names
        no master): the runtime's and the simulation's drone say it alike."""
        master = metadata.get("baton-master")
        if master is None:
            return None
        grant_hex = str(metadata.get("baton-grant", ""))
        lognr, _, epoch = str(metadata.get("baton-takeover-holds", "0/0")).partition("/")
        return cls(
            int(str(master)),
            int(str(metadata.get("baton-epoch", "0"))),
            int(str(metadata.get("baton-after-reqnr", "0"))),
            str(metadata.get("baton-takeover", "")) == "1",
            int(str(metadata.get("baton-takeover-epoch", "0"))),
            drone_pb2.Grant.FromString(bytes.fromhex(grant_hex)) if grant_hex else None,
            int(str(metadata.get("baton-takeover-watermark", "0"))),
            (int(lognr or 0), int(epoch or 0)),
        )

    @classmethod
    def of_status(
        cls, code: grpc.StatusCode, metadata: Mapping[str, str | bytes]
    ) -> DroneRefusal | None:
        """The refusal a failed drone call states: a FAILED_PRECONDITION naming a master."""
        if code is not grpc.StatusCode.FAILED_PRECONDITION:
            return None
        return cls.from_metadata(metadata)

    @property
    def fencing_epoch(self) -> int:
        """The epoch of the takeover that fences the refused controller (``on_fenced``):
        the newest takeover's, not the drone's epoch now. A handover message of a
        mastership granted after that takeover is a role the drone gave since, which
        the rejoining controller's fresh self must keep
        (``ControllerProtocol.kept_for_rejoin``)."""
        return self.takeover_epoch or self.epoch


@dataclass(frozen=True)
class Reconnect:
    """Effect: close the drone session (if any) and open a new one, to hear a new epoch."""


@dataclass(frozen=True)
class Rejoin:
    """Effect: rejoin as a replica with nothing (``ControllerNode.reset``), as a task of its
    own: it stops the mission program, whose call may be what led here."""


@dataclass(frozen=True)
class SendCatchUp:
    """Effect: send ``target`` straight what it may lack of our history (cut-through)."""

    target: int


@dataclass(frozen=True)
class Record:
    """Effect (bookkeeping): a role this controller took in a handover, for its status."""

    role: ring_pb2.HandoverRole.ValueType
    other: int
    lognr: int
    reqnr: int
    log_bytes: int
    epoch: int = 0
    drone_after_reqnr: int = 0
    holds_reqnr: int = 0


@dataclass(frozen=True)
class Note:
    """Effect: something a person may want to read (the runtime's log, the simulation's
    trace); ``level`` is ``debug``, ``info``, ``warning`` or ``error``."""

    level: str
    text: str
    fields: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class RepairGap:
    """Effect: make our predecessors connect again (every incoming ring stream dropped),
    so that they hear our hello and re-send what is above what we hold."""


@dataclass(frozen=True)
class SayWord:
    """Effect: the master's word we say on changed (``ControllerProtocol.master_word``):
    our successor's stream says it in a sync frame (``LinkCore.sync_due``)."""


@dataclass(frozen=True)
class RouteTo:
    """Effect: send the ring's messages to ``successor`` from now on, skipping ``skipped``
    (the links follow: the new successor's stream carries the history)."""

    successor: int
    skipped: list[int]
    previous: int  # the successor before
    natural: int  # the successor in ring order

    @property
    def retired(self) -> int | None:
        """A successor routed to before and neither the natural one nor skipped now: its
        stream ends once it has nothing unacknowledged (the ring came back past it)."""
        if self.previous == self.natural or self.previous in self.skipped:
            return None
        return self.previous


@dataclass(frozen=True)
class Preparing:
    """Effect: a prepared handover to ``target`` began (``ControllerCore.prepare``): count
    the acknowledgements of the stream to it from now (its end is a ``Timer.PREPARATION``)."""

    target: int
    epoch: int


class Timer(enum.Enum):
    """A decision the core takes at a time it knows in advance (``Arm``)."""

    # A log message missing while later ones are queued: its repair (``gap_due``).
    GAP = "gap"
    # A ring stream down: when it has been down for the detection time; a route held
    # back: when the hold ends (``route``).
    ROUTE = "route"
    # A prepared handover: its time is up (``preparation_over``).
    PREPARATION = "preparation"


# In the order ``ControllerCore._arm`` compares their deadlines.
TIMERS = (Timer.GAP, Timer.ROUTE, Timer.PREPARATION)


@dataclass(frozen=True)
class Arm:
    """Effect: call ``ControllerCore.timer_fired(timer, ...)`` at ``at`` (the driver's
    monotonic clock, as every time the core is given). One deadline per timer: arming
    it again replaces the pending one."""

    timer: Timer
    at: float


@dataclass(frozen=True)
class Disarm:
    """Effect: the pending deadline of ``timer`` is moot; it must not fire."""

    timer: Timer


@dataclass(frozen=True)
class RingSight:
    """What a driver sees of its links when the core decides about the route or a gap
    (``ring_changed``, ``timer_fired``): nothing the core could know by itself."""

    # The ring links that carry something (``LinkCore.used``) and are down, and since
    # when (``LinkCore.down_since``); an up or unused link is absent.
    down_since: Mapping[int, float]
    # Whether the drone's Connect stream is up.
    drone_connected: bool
    # When a frame of each log message on its way last arrived (cut-through).
    frames_at: Mapping[int, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Fail:
    """Effect: the mission stops here with ``text`` (the controller cannot go on)."""

    text: str
    code: grpc.StatusCode = grpc.StatusCode.INTERNAL


@dataclass(frozen=True)
class Keep:
    """Effect: keep ``message`` in the history (what a successor that restarts is given
    again); the successor's stream then says what we hold."""

    message: ring_pb2.LogMessage
    proof: bytes = b""  # its holding_proof, computed with its check (b"": not computed)


@dataclass(frozen=True)
class SettleHandovers:
    """Effect: our handover messages still unacknowledged whose role is settled (the
    ring went on past them: ``ControllerProtocol.handover_settled``) lose their flag on
    the direct link and enter the history, as on an acknowledgement."""


@dataclass(frozen=True)
class Seen:
    """Effect: the protocol consumed ``entry``: it is the program's answer, on every
    replica (counted into the reply chain where it is consumed, not where the program
    gets it, so a call cancelled after that counts as on every replica).

    ``replayed``: consumed from the replayed log, which holds more after it. Such a
    step changes only the log's entries and the request number, which no deadline
    and no mastership reads (``ready``)."""

    entry: ring_pb2.LogEntry
    replayed: bool = False


@dataclass(frozen=True)
class ReplayAgain:
    """Effect: the program gave up (``code``) on a call whose entry is not that give-up
    (the master's program, or a lost master's, got ``entry``): it has acted on nothing
    the mission did not, and starts again from the log (the rejoin comes with it); its
    call fails ABORTED."""

    entry: ring_pb2.LogEntry
    method: str
    code: grpc.StatusCode


@dataclass(frozen=True)
class FirstNewCall:
    """Effect (bookkeeping): a takeover's first call not answered from the retained
    replies, the end of the takeover (``baton bench failover`` reads it)."""

    reqnr: int
    method: str
    epoch: int


# What ``ControllerCore.answer`` says of the program's call.
@dataclass(frozen=True)
class Answer:
    """The call's answer is ``entry`` (replayed, or logged now)."""

    entry: ring_pb2.LogEntry


@dataclass(frozen=True)
class Hold:
    """The call waits for a change: the log (not ACTIVE: ``reqnr`` 0), or, ACTIVE with
    request ``reqnr`` next, the drone's grant or the replies it retains."""

    reqnr: int = 0


@dataclass(frozen=True)
class AskClock:
    """Request ``reqnr`` is the controller's own Clock call: answer it, then ``logged``."""

    reqnr: int
    digest: bytes

    def entry(self, method: str, request: bytes, reply: bytes) -> ring_pb2.LogEntry:
        """The log entry of the Clock's ``reply`` to the call."""
        return ring_pb2.LogEntry(
            reqnr=self.reqnr,
            method=method,
            reply=reply,
            request_digest=self.digest,
            request=request,
        )


@dataclass(frozen=True)
class AskDrone:
    """Request ``reqnr`` goes to the drone: invoke it, then ``logged`` (or ``answer``
    again if the drone's answer changed the state)."""

    reqnr: int
    digest: bytes


CallStep = Answer | Hold | AskClock | AskDrone


@dataclass(frozen=True)
class Persist:
    """Effect: ``message`` enters the history (and the successor's stream is told what we
    hold now), before it is sent (``ControllerCore.ready``)."""

    message: ring_pb2.LogMessage
    proof: bytes = b""  # its holding_proof, computed with its signature (SendLog.proof)


@dataclass(frozen=True)
class KeepMastership:
    """Effect: the mastership whose log the history holds, kept with it, so that a restart
    from the file tells the drone on Connect (fenced if a takeover replaced it)."""

    epoch: int


CoreEffect = (
    Effect
    | Persist
    | KeepMastership
    | Reconnect
    | Rejoin
    | SendCatchUp
    | Record
    | Note
    | Fail
    | RepairGap
    | SayWord
    | RouteTo
    | Preparing
    | Arm
    | Disarm
    | Keep
    | SettleHandovers
    | Seen
    | ReplayAgain
    | FirstNewCall
)

# A master stops a prepared handover this long after the drone's timeout for it, if it
# heard nothing (the drone forces the handover at its timeout: the notice is owed).
PREPARE_GRACE_S = 2.0


class HeldLog(Protocol):
    """What the core reads of the log messages a controller holds (its ``LogHistory``),
    as raft's core reads its ``Storage``: it never writes them."""

    def above(self, lognr: int) -> Iterator[int]: ...

    def get(self, lognr: int) -> ring_pb2.LogMessage: ...


class ControllerCore:
    """A controller's protocol and what it knows of its drone session."""

    def __init__(
        self,
        protocol: ControllerProtocol,
        cut_through: bool = False,
        max_sleep_s: float = math.inf,
        detection_s: float = 0.0,
    ) -> None:
        self.protocol = protocol
        # How long a ring stream is down before the ring routes around it (0: never),
        # and how long a gap stays before its repair (``gap_repair_s``).
        self.detection_s = detection_s
        self.repair_s = gap_repair_s(detection_s)
        # The deadline of each timer armed (``Arm``), as the driver holds it; and the
        # deadlines a step last left (GAP, ROUTE, PREPARATION), while ``armed`` is them.
        self.armed: dict[Timer, float] = {}
        self._deadlines: tuple[float | None, ...] | None = (None, None, None)
        # Check the masterships' legal combinations at every step (``ready``).
        self.checking = checking()
        # The longest Clock.Sleep the mission may ask (``safety.max_sleep``).
        self.max_sleep_s = max_sleep_s
        # The ring forwards frames as they come: a handover's new master is sent
        # what it may lack straight away (``handover_notice``).
        self.cut_through = cut_through
        # The epoch of the takeover the drone told us of (TakeOver), and its watermark.
        self.takeover_epoch = 0
        self.takeover_watermark = 0
        # The replies the drone retains for us above what we hold (after Connected),
        # by reqnr, up to ``retained_through``; ``retained_due`` is the last the drone
        # said it sends, ``retained_came`` the last that came.
        self.retained: dict[int, drone_pb2.RetainedReply] = {}
        self.retained_through = 0
        self.retained_due = 0
        self.retained_came = 0
        # A takeover's first call that is not answered from the retained replies
        # says which retained replies it adopted (InvokeRequest.adopted_from_reqnr).
        self.first_new_call_due = False
        # A framing of ours the drone replaced: refused by every fresh self.
        self.replaced: ReplacedFraming | None = None
        # A rejoin is under way (``Rejoin`` given, the runtime not done with it).
        self.rejoining = False
        # The gap in what we received being repaired (``gap_due``): the missing log
        # number, since when it is missing, when to act next.
        self.gap: tuple[int, float, float] | None = None
        # The successors the ring routes around now (``route_due``); when the route is
        # to be decided again (a down stream reaching the detection time); whether a
        # route around is held back (``ControllerProtocol.may_route_around``).
        self.routed_around: list[int] = []
        self.route_at: float | None = None
        self.route_held = False
        # The prepared handover under way (``prepare``): the drone's bound for its
        # target (0: no words between requests), and when we stop on our own.
        self.prepare_bound = 0
        self.prepare_until = 0.0
        # The preparation whose end is armed: its target and epoch (None: none, or spent).
        self.prepared: tuple[int, int] | None = None
        # The program's calls given up while this controller waited, in order: each is
        # settled by the next call (``settle``) with the entry the log gives it.
        self.abandoned: deque[tuple[str, bytes, grpc.StatusCode]] = deque()
        # The first request answered from the retained replies in a mastership of ours
        # and not yet carried to the drone by a call it answered:
        # InvokeRequest.adopted_from_reqnr (the drone counts them as brought in the
        # call's epoch). 0: none.
        self.adopted = 0
        # The Clock calls (and give-ups) consumed since the last drone call: sent
        # along with the next Invoke, so the drone keeps them for a taker.
        self.answered_here: list[ring_pb2.LogEntry] = []
        self.answered_from_retained = 0
        # The drone call asked last, and the watermark it carries at the least: the
        # drone's reply to it says the drone took that much (``logged``).
        self.asked_with = (0, 0)
        # The last log number sent straight to each handover target (``catch_up`` and a
        # prepared handover's copies), so that none is sent to it twice.
        self.sent_straight: dict[int, int] = {}
        # The master's word as the last step left it (``SayWord``).
        self._word = (0, 0)
        # Checks every log message's creator's signature and the drone's of every
        # reply it brings (baton.authenticity); None: insecure, a station's word is taken.
        self.keys: Keys | None = None
        # The log messages refused for it, and the last refusal in words.
        self.refused_messages = 0
        self.last_refused = ""
        # Sync frames whose words were not believed (``sync_arrived``), the last one in
        # words, and the stations already named in the log for it (once each).
        self.refused_words = 0
        self.last_refused_word = ""
        self._named_liars: set[int] = set()

    def fresh_self(self) -> ControllerCore:
        """The core of this controller rejoining with nothing (``ControllerProtocol.
        fresh_self``), refusing the framing the drone replaced, if any."""
        fresh = ControllerCore(
            self.protocol.fresh_self(), self.cut_through, self.max_sleep_s, self.detection_s
        )
        fresh.replaced = self.replaced
        fresh.keys = self.keys
        fresh.refused_messages, fresh.last_refused = self.refused_messages, self.last_refused
        fresh.refused_words, fresh.last_refused_word = self.refused_words, self.last_refused_word
        fresh._named_liars = self._named_liars
        if self.replaced is not None:
            fresh.protocol.refuse_replaced(self.replaced)
        return fresh

    def ready(
        self,
        effects: Sequence[CoreEffect],
        drone_connected: bool,
        now: float,
        drone_reachable: bool = True,
    ) -> list[CoreEffect]:
        """What a driver carries out for ``effects``, in this order (etcd raft's ``Ready``);
        ``drone_reachable``: either stream to the drone is up (the Connect or the standby).

        - A log message we send enters the history first (``Persist``), except a
          handover message: it enters when it comes back round, once its new master
          has it; a history copy re-sent to the successor before then could overtake
          it, and the new master would take the copy for a normal message.
        - A copy for a prepared handover's target goes only while the drone's stream
          is up: cut off, a takeover may have replaced us, and the copy would pass the
          taker's fence on the ring. A new stream's PrepareHandover catches the
          target up; a refused one fences us.
        - A log that diverged from the ring's makes us rejoin with nothing, once.
        - Cut off from the drone, a queued message of a newer mastership fences us
          (``went_on_without_us``): the state after any event may show it.
        - Then the mastership whose log we hold is kept with the log, and a changed
          master's word is said on to the successor (``SayWord``).
        - Last, the timers whose deadline the step changed (``Arm``, ``Disarm``).
        - A step that only answers a replayed call (``Seen.replayed``) is carried out
          as it is: it moved no deadline and no mastership.

        With ``checking`` (``BATON_CHECK_INVARIANTS=1``), the masterships the step
        left must be a legal combination (``Mastership.problems``), or
        ``InvariantBroken``: a defect of baton, which the driver stops on.
        """
        if not drone_reachable and not self.rejoining:
            effects = [*effects, *self.went_on_without_us(self.protocol.went_on_in_queue(), False)]
        if len(effects) == 1 and isinstance(effects[0], Seen) and effects[0].replayed:
            # A replayed answer alone: nothing to persist, keep or arm (``Seen.replayed``).
            out = list(effects)
        else:
            out = self._ready(effects, drone_connected, now)
        if self.checking:
            problems = self.protocol.mastership.problems()
            if problems:
                raise InvariantBroken(
                    f"controller {self.protocol.id}: {'; '.join(problems)} "
                    f"({self.protocol.mastership})"
                )
        return out

    def _ready(
        self, effects: Sequence[CoreEffect], drone_connected: bool, now: float
    ) -> list[CoreEffect]:
        out: list[CoreEffect] = []
        for effect in effects:
            if isinstance(effect, SendLog):
                if effect.copy and not drone_connected:
                    continue
                if effect.copy:
                    self.sent_straight[effect.dest] = effect.message.lognr
                elif not effect.message.handover:
                    out.append(Persist(effect.message, effect.proof))
            out.append(effect)
            if isinstance(effect, Diverged):
                out.extend(self.rejoin())
        out.append(KeepMastership(self.protocol.log_mastership_epoch))
        word = self.protocol.master_word
        if word != self._word:
            # Said on whatever else the step did: a word heard from the ring that drops
            # nothing here may drop a stale queued message further on, and a taker gone
            # ACTIVE with nothing to log has no message to carry its word.
            self._word = word
            out.append(SayWord())
        self._arm(now, drone_connected, out)
        return out

    def catch_up(self, target: int, held: HeldLog) -> list[ring_pb2.LogMessage] | None:
        """What a handover's target is sent straight from us (``SendCatchUp``), or None
        when the target is our successor, whose ring stream gives it everything in order.

        Our messages the ring has not yet brought back to us (above ``acked_lognr``),
        of our mastership, and not sent to it already, before what follows (the
        handover message, or a prepared handover's flushes): one link's time, not one
        per hop (docs/design.md, "The ring's forwarding"). The target ignores what it
        has. Not the messages of earlier masterships we passed on: they went on along
        the ring before ours, and a copy of each would cross the target's link a second
        time, ahead of ours (a signed ring's ``acked_lognr`` counts our own messages
        only, so nothing else bounds them).
        """
        p = self.protocol
        if target == p.successor:
            return None
        sent = max(p.acked_lognr, self.sent_straight.get(target, 0))
        # Masters number log messages in the order of their epochs: read from the top
        # down, the first of an earlier mastership ends ours (the history is not read
        # whole at every handover).
        messages: list[ring_pb2.LogMessage] = []
        for lognr in sorted(held.above(sent), reverse=True):
            message = held.get(lognr)
            if message.epoch < p.epoch:
                break
            messages.append(message)
        messages.reverse()
        if messages:
            self.sent_straight[target] = messages[-1].lognr
        return messages

    def kept_on_rejoin(self, held: HeldLog) -> list[ring_pb2.LogMessage]:
        """What a controller that rejoins with nothing gives its fresh self, in order: a
        fenced controller's messages that went round the ring (maybe the one copy
        left: ``kept_when_fenced``), a master whose program starts again its whole log
        (``restart_program``), then the handover messages that exist nowhere else."""
        upto = self.protocol.kept_history()
        kept = [held.get(lognr) for lognr in held.above(0) if lognr <= upto]
        return kept + self.protocol.kept_for_rejoin()

    # -- the drone's word ------------------------------------------------------------

    def granted(self, connected: drone_pb2.Connected) -> list[CoreEffect]:
        """The drone's Connected event: master in its ``epoch`` (``grant``: its word,
        signed). The retained replies above what we hold follow, up to
        ``retained_through`` (``retained_batch``); a takeover's grant must hold every
        request up to the watermark before it goes ACTIVE.
        Raises ProtocolError as ``ControllerProtocol.on_granted`` does."""
        p = self.protocol
        epoch, retained_through = connected.epoch, connected.retained_through
        takeover, takeover_epoch = connected.takeover, connected.takeover_epoch
        grant = connected.grant if connected.HasField("grant") else None
        if connected.replaced_from_lognr:
            by = connected.replaced_by_epoch
            replaced = ReplacedFraming(0, connected.replaced_from_lognr, by - 1, by)
            return self._rejoin_refusing(replaced, "the drone")
        if p.log_given_up(takeover_epoch) and not p.taken_back(epoch, takeover, takeover_epoch):
            note = Note(
                "warning",
                "granted while ACTIVE in a mastership a takeover replaced: rejoining with "
                "nothing before taking the role",
                {"epoch": epoch, "our_epoch": p.epoch, "takeover_epoch": takeover_epoch},
            )
            return [note, *self.fenced(self.protocol.id, takeover_epoch)]
        held = p.held_reqnr
        self.retained = {}
        self.retained_through = retained_through if retained_through > held else 0
        self.retained_due, self.retained_came = retained_through, 0
        was_active = p.state is State.ACTIVE
        takeover = takeover or epoch == self.takeover_epoch
        self.first_new_call_due = takeover
        watermark = max(self.takeover_watermark, connected.watermark_reqnr)
        effects: list[CoreEffect] = list(p.on_granted(epoch, takeover, watermark, grant))
        if not was_active:
            fields = {"epoch": epoch, "takeover": takeover, "caught_up": p.caught_up}
            effects.insert(0, Note("info", "the drone says this controller is master", fields))
        return effects

    def retained_batch(self, replies: Sequence[drone_pb2.RetainedReply]) -> list[CoreEffect]:
        """A batch of the replies the drone retains for us, in order (after Connected)."""
        held = self.protocol.held_reqnr
        if replies:
            self.retained_came = max(self.retained_came, replies[-1].reqnr)
        refused = self._refuse_replaced(replies)
        if refused:
            return refused
        self.retained.update((kept.reqnr, kept) for kept in replies if kept.reqnr > held)
        return []

    def _refuse_replaced(self, replies: Iterable[drone_pb2.RetainedReply]) -> list[CoreEffect]:
        """A rejoin refusing our framing of a request the drone keeps in a newer one
        (``ControllerProtocol.replaced_framing``); nothing if there is none."""
        replaced = self.protocol.replaced_framing(list(replies))
        return [] if replaced is None else self._rejoin_refusing(replaced, "the retained replies")

    def _rejoin_refusing(self, replaced: ReplacedFraming, said_by: str) -> list[CoreEffect]:
        """A rejoin whose fresh self refuses our framing from ``replaced.lognr`` on
        (``ControllerProtocol.refuse_replaced``): a later takeover replaced it, as the
        drone's retained replies (another outcome of a request, brought in a newer
        epoch) or its grant (the ring's messages numbered from there are of a newer
        epoch) say."""
        self.replaced = replaced
        note = Note(
            "warning",
            "we hold a framing a later takeover replaced; rejoining as a replica that "
            "refuses that framing from its log message on",
            {
                "said_by": said_by,
                "reqnr": replaced.reqnr,
                "lognr": replaced.lognr,
                "framed_in": replaced.ours_epoch,
                "drone_epoch": replaced.epoch,
                "epoch": self.protocol.epoch,
            },
        )
        return [note, *self.rejoin()]

    def take_over(self, event: drone_pb2.TakeOver) -> list[CoreEffect]:
        """The drone made us master by takeover (the standby stream's TakeOver): connect
        again to learn the epoch; the replies we lack follow the Connected."""
        p = self.protocol
        old_master, epoch = event.old_master, event.epoch
        after_reqnr, watermark_reqnr = event.after_reqnr, event.watermark_reqnr
        self.takeover_epoch = epoch
        self.takeover_watermark = watermark_reqnr
        fields = {
            "old_master": old_master,
            "epoch": epoch,
            "drone_after_reqnr": after_reqnr,
            "watermark_reqnr": watermark_reqnr,
            "holds_reqnr": p.held_reqnr,
        }
        return [
            Record(
                ring_pb2.HANDOVER_ROLE_TAKER,
                old_master,
                p.lognr,
                p.reqnr,
                p.log.size,
                epoch=epoch,
                drone_after_reqnr=after_reqnr,
                holds_reqnr=p.held_reqnr,
            ),
            Note("warning", "taking over from a lost master", fields),
            Reconnect(),
        ]

    def fenced(
        self,
        new_master: int,
        epoch: int,
        watermark: int = 0,
        taker_holds: tuple[int, int] = (0, 0),
    ) -> list[CoreEffect]:
        """Our mastership was taken over (in ``epoch``; ``watermark``: the drone's at that
        takeover, 0 if not said; ``taker_holds``: the message the taker built on):
        stop acting as master, then rejoin as a replica with nothing but what
        ``ControllerProtocol.kept_when_fenced`` keeps; nothing if a rejoin is under
        way."""
        if self.rejoining:
            return []
        p = self.protocol
        if p.master and 0 < epoch <= p.epoch:
            # A takeover of a mastership older than the one we hold now (handed back
            # to us by a handover message since, ``_take_handed_back``, or one that
            # made us master and we are catching up for) fences nothing: connect
            # again, in our epoch, to hear the drone's word of it.
            fields = {"fencing_epoch": epoch, "epoch": p.epoch}
            return [
                Note("info", "a takeover older than our mastership; connecting again", fields),
                Reconnect(),
            ]
        note = Note(
            "warning",
            "fenced: the drone gave our mastership to another controller by takeover; "
            "dropping what we hold beyond the ring and rejoining as a replica",
            {"new_master": new_master, "epoch": epoch, "unflushed_entries": len(p.log)},
        )
        record = Record(ring_pb2.HANDOVER_ROLE_FENCED, new_master, p.lognr, p.reqnr, p.log.size)
        return [record, note, *p.on_fenced(epoch, watermark, taker_holds), *self.rejoin()]

    def rejoin(self) -> list[CoreEffect]:
        """A rejoin with nothing, unless one is under way."""
        if self.rejoining:
            return []
        self.rejoining = True
        return [Rejoin()]

    def connect_refused(self, refusal: DroneRefusal) -> list[CoreEffect]:
        """Connect refused: another controller is master, and no notice is owed to us."""
        p = self.protocol
        if refusal.taken_over or p.log_given_up(refusal.takeover_epoch):
            return self.fenced(
                refusal.master,
                refusal.fencing_epoch,
                refusal.takeover_watermark,
                refusal.taker_holds,
            )
        if p.state is not State.ACTIVE:
            fields = {"master": refusal.master, "epoch": refusal.epoch}
            return [Note("info", "not the master", fields), DisconnectDrone()]
        if p.connect_refusal_is_stale(refusal.epoch):
            # Asked before the drone made us master, answered after: ask again.
            note = Note("info", "stale Connect refusal; connecting again", {"epoch": refusal.epoch})
            return [note, Reconnect()]
        # Made master by a handover message, but the drone moved on meanwhile: the
        # log goes to the master it names.
        return self.handover_notice(
            refusal.master, refusal.after_reqnr, refusal.epoch, refusal.grant
        )

    def request_refused(
        self, sent_epoch: int, refusal: DroneRefusal, reqnr: int, method: str, detail: str
    ) -> list[CoreEffect]:
        """The drone refused request ``reqnr``, sent in ``sent_epoch``, naming a master
        (``ControllerProtocol.judge_refusal``): the log and the drone disagree (the
        mission stops), another master now (fenced, or a handover notice), ourselves
        again in a newer epoch (connect again to learn it), or a stale refusal."""
        p = self.protocol
        verdict = p.judge_refusal(sent_epoch, refusal.master, refusal.epoch)
        if verdict is Refusal.DISAGREE:
            # The drone knows us as master, in this epoch, yet refused the request
            # number: the log and the drone disagree.
            return [
                Fail(f"controller {p.id}: the drone refused request {reqnr} ({method}): {detail}")
            ]
        if verdict is Refusal.HANDED_OVER:
            if refusal.taken_over or p.log_given_up(refusal.takeover_epoch):
                return self.fenced(
                    refusal.master,
                    refusal.fencing_epoch,
                    refusal.takeover_watermark,
                    refusal.taker_holds,
                )
            return self.handover_notice(
                refusal.master, refusal.after_reqnr, refusal.epoch, refusal.grant
            )
        if verdict is Refusal.REGRANTED:
            fields = {"sent_epoch": sent_epoch, "drone_epoch": refusal.epoch}
            return [
                Note("info", "master again in a newer epoch; connecting again", fields),
                Reconnect(),
            ]
        fields = {"reqnr": reqnr, "sent_epoch": sent_epoch, "drone_epoch": refusal.epoch}
        return [Note("info", "stale request refused by the drone", fields)]

    def stream_notice(self, notice: drone_pb2.HandoverNotice) -> list[CoreEffect]:
        """A handover notice on the Connect stream (the drone owes at most one, the latest).

        A takeover's notice fences us (``takeover_watermark_reqnr``: the drone's at that
        takeover); so does one whose drone took over after our mastership
        (``takeover_epoch``, ``ControllerProtocol.log_given_up``): our log was replaced
        by the taker's framing, and handing it over would put a second framing of the
        same requests on the ring."""
        new_master, after_reqnr, epoch = notice.new_master, notice.after_reqnr, notice.epoch
        takeover, takeover_epoch = notice.takeover, notice.takeover_epoch
        takeover_watermark = notice.takeover_watermark_reqnr
        grant = notice.grant if notice.HasField("grant") else None
        if takeover:
            return self.fenced(new_master, epoch, takeover_watermark)
        if self.protocol.log_given_up(takeover_epoch):
            return self.fenced(new_master, takeover_epoch)
        if self.protocol.state is State.ACTIVE:
            return self.handover_notice(new_master, after_reqnr, epoch, grant)
        return [DisconnectDrone()]  # a notice for a mastership we no longer hold

    def handover_notice(
        self,
        new_master: int,
        after_reqnr: int,
        epoch: int,
        grant: drone_pb2.Grant | None = None,
    ) -> list[CoreEffect]:
        """The drone chose another master (Algorithm 1, lines 24-29): the unflushed log
        goes to it with the handover flag and the drone's ``grant`` of ``epoch`` to it,
        and with cut-through what it may lack of our history first. Nothing for a stale
        notice, or when not ACTIVE."""
        p = self.protocol
        if p.state is not State.ACTIVE:
            return []
        log_bytes = p.log.size
        try:
            effects = p.on_handover_notice(new_master, epoch, grant)
        except ProtocolError as exc:
            return [Note("error", "bad handover notice", {"error": str(exc)})]
        if p.state is State.ACTIVE:
            # A notice of a switch before our mastership (a takeover made us master
            # since): stale, nothing handed over.
            fields = {"new_master": new_master, "notice_epoch": epoch, "epoch": p.epoch}
            return [Note("warning", "stale handover notice ignored", fields)]
        record = Record(
            ring_pb2.HANDOVER_ROLE_OLD,
            new_master,
            p.lognr,
            p.reqnr,
            log_bytes,
            epoch=epoch,
            drone_after_reqnr=after_reqnr,
        )
        fields = {
            "new_master": new_master,
            "drone_after_reqnr": after_reqnr,
            "log_bytes": log_bytes,
        }
        catch_up: list[CoreEffect] = [SendCatchUp(new_master)] if self.cut_through else []
        return [record, Note("info", "handing over", fields), *catch_up, *effects]

    def log_arrived(
        self,
        message: ring_pb2.LogMessage,
        drone_reachable: Callable[[], bool],
        relayed_by: int = 0,
    ) -> list[CoreEffect]:
        """A log message from the ring or from an old master (Algorithm 1, lines 30-47):
        kept in the history unless it is from a fenced master or diverged from ours;
        forwarded and handled (``ControllerProtocol.on_log``); a message we cannot
        handle stops our mission but is still forwarded (the replicas after us go on);
        a message that shows our mastership went on without us fences us if the drone
        is out of reach (``drone_reachable``, asked then: ``went_on_without_us``)."""
        p = self.protocol
        # The replies hashed once, for the signatures' check and the proof of holding.
        hashes = reply_hashes(message) if self.keys is not None else None
        refused = self.unsigned(message, relayed_by, hashes)
        if refused:
            return refused
        proof = holding_proof(message, hashes) if hashes is not None else b""
        try:
            effects = p.on_log(message)
        except ProtocolError as exc:
            return [Keep(message, proof), Fail(f"controller {p.id}: {exc}"), *exc.effects]
        dropped = any(isinstance(effect, Fenced | Diverged) for effect in effects)
        kept: list[CoreEffect] = [] if dropped else [Keep(message, proof)]
        fenced: list[CoreEffect] = []
        if p.went_on_without_us(message):  # asked of the driver only then
            fenced = self.went_on_without_us(message, drone_reachable())
        return [*kept, *effects, SettleHandovers(), *fenced]

    def unsigned(
        self,
        message: ring_pb2.LogMessage,
        relayed_by: int = 0,
        hashes: list[bytes] | None = None,
    ) -> list[CoreEffect]:
        """A log message its creator did not sign, or with a reply the drone did not sign
        (forged or altered by a station): refused whole, before it touches the log, the
        history or the ring (not forwarded: a relay of it is dropped), named by the
        station that relayed it (``relayed_by``, the ring stream's; 0: our own history)
        and why. Nothing if it is signed throughout, or we check no signatures.
        ``hashes``: the replies' SHA-256 (``reply_hashes``) if the caller has them."""
        if self.keys is None:
            return []
        why = refusal(self.keys, message, self.protocol.id, hashes)
        if why is None:
            return []
        self.refused_messages += 1
        self.last_refused = (
            f"log message {message.lognr} (origin {message.origin}, epoch {message.epoch}) "
            f"relayed by controller {relayed_by}: {why}"
        )
        fields = {
            "mlognr": message.lognr,
            "origin": message.origin,
            "relayed_by": relayed_by,
            "why": why,
        }
        return [Note("error", "log message refused: not signed as it says", fields)]

    def sync_arrived(self, sender: int, word: SyncWord) -> list[CoreEffect]:
        """A ring stream's sync frame from controller ``sender``: what it holds and the
        newest master it knows of, handled as far as they are believed
        (``sync_words.believe``; ``ControllerProtocol.on_sync``). A word not believed is
        counted (``refused_words``, ``last_refused_word``) and logged once per station:
        it changes nothing, so a station that keeps lying costs a counter, not a log."""
        belief = believe(self.keys, word)
        refused = list(belief.refused)
        if self.keys is not None and self.protocol.unproved_word(
            word.holds, word.holds_epoch, word.holds_proof
        ):
            refused.append(f"it says it holds our message {word.holds} without the proof")
        effects: list[CoreEffect] = []
        if refused:
            self.refused_words += 1
            why = "; ".join(refused)
            self.last_refused_word = f"sync frame from controller {sender}: {why}"
            if sender not in self._named_liars:
                self._named_liars.add(sender)
                fields = {"sender": sender, "why": why}
                effects.append(Note("error", "sync frame's words not believed", fields))
        w = belief.word
        return effects + self.protocol.on_sync(
            w.holds,
            w.holds_epoch,
            w.master_epoch,
            w.master_lognr,
            w.holds_proof,
            w.master_proof,
            belief.holds_backed,
        )

    def went_on_without_us(
        self, message: ring_pb2.LogMessage | None, drone_reachable: bool
    ) -> list[CoreEffect]:
        """``message`` (if any) shows our mastership went on without our log: fenced, if we
        are cut off from the drone (neither stream up). With either stream up the drone
        tells us itself; cut off, it cannot, and a master stranded ACTIVE would follow
        the ring no more."""
        if message is None or drone_reachable:
            return []
        fields = {
            "mlognr": message.lognr,
            "origin": message.origin,
            "epoch": message.epoch,
            "our_epoch": self.protocol.epoch,
        }
        note = Note(
            "warning",
            "the ring carries a newer mastership than ours while the drone is out of reach: "
            "taken over",
            fields,
        )
        return [note, *self.fenced(message.origin, message.epoch)]

    # -- a prepared handover (docs/design.md, "Prepared handover") ----------------------

    def prepare(self, prepare: drone_pb2.PrepareHandover, now: float) -> list[CoreEffect]:
        """The drone plans a handover to its ``target``: it is caught up straight from us
        while the mission goes on; the drone moves the master once it lacks at most
        ``bound_bytes`` (``progress`` on every Invoke, ``report_due`` between them). If
        we hear nothing by the drone's timeout and a grace (its notice is owed on our
        stream), we stop flushing every entry (``preparation_over``). Nothing if we are
        not ACTIVE in its ``epoch`` (the drone's word came late)."""
        p = self.protocol
        target, epoch, timeout_s = prepare.target, prepare.epoch, prepare.timeout_s
        bound_bytes = prepare.bound_bytes
        try:
            effects = p.on_prepare(target, epoch)
        except ProtocolError as exc:
            return [Note("error", "bad prepare-handover event", {"error": str(exc)})]
        if p.preparing_for != target:
            return []
        self.prepare_bound = bound_bytes
        self.prepare_until = now + timeout_s + PREPARE_GRACE_S
        self.prepared = (target, epoch)
        note = Note("info", "preparing a handover", {"target": target, "timeout_s": timeout_s})
        return [note, Preparing(target, epoch), SendCatchUp(target), *effects]

    def preparation_over(self, target: int, epoch: int, until: float) -> list[CoreEffect]:
        """The time of the preparation for ``target`` in ``epoch`` is up, unless a newer
        preparation (the drone replaced it, perhaps by one with the same target) gave
        more (a later ``prepare_until``)."""
        p = self.protocol
        if until < self.prepare_until:
            return []
        if p.preparing_for != target or p.epoch != epoch:
            return []
        p.end_preparation()
        note = Note(
            "warning",
            "a prepared handover was not carried out in its time; flushing as usual",
            {"target": target},
        )
        return [note]

    def progress(
        self, unacked_bytes: int | None, behind_s: float = 0.0, acked: int = 0
    ) -> drone_pb2.PreparationProgress | None:
        """How far a prepared handover's target is behind us (None: not preparing):
        ``unacked_bytes`` on the stream to it (None: no stream to it), how long its
        oldest unacknowledged message has waited, and its acknowledgements since the
        preparation began."""
        p = self.protocol
        target = p.preparing_for
        if target is None:
            return None
        lacks = (unacked_bytes or 0) + p.log.size
        if unacked_bytes is None:
            return drone_pb2.PreparationProgress(
                target=target, lacks_bytes=lacks, after_reqnr=p.reqnr
            )
        return drone_pb2.PreparationProgress(
            target=target, lacks_bytes=lacks, after_reqnr=p.reqnr, behind_s=behind_s, acked=acked
        )

    def report_due(self, peer_id: int, progress: drone_pb2.PreparationProgress | None) -> bool:
        """Whether an acknowledgement from ``peer_id`` is worth a word to the drone between
        requests (``ReportPreparation``): it is the target, and lacks at most the bound."""
        if peer_id != self.protocol.preparing_for or not self.prepare_bound:
            return False
        return progress is not None and progress.lacks_bytes <= self.prepare_bound

    # -- the mission program's calls ---------------------------------------------------

    def consume(self, entry: ring_pb2.LogEntry, replayed: bool = False) -> Seen:
        """The protocol consumed ``entry`` as the program's answer: a Clock answer or a
        give-up goes along with the next drone call, a drone call clears them."""
        if entry.method.startswith(CLOCK_SERVICE) or entry.given_up:
            self.answered_here.append(entry)
        else:
            self.answered_here.clear()
        return Seen(entry, replayed)

    def ours_to_log(self, reqnr: int) -> bool:
        """Still ACTIVE, with ``reqnr`` the next request to log."""
        p = self.protocol
        return p.state is State.ACTIVE and p.reqnr + 1 == reqnr

    def retained_pending(self, reqnr: int) -> bool:
        """Whether the drone's retained reply for ``reqnr`` is still to come, or (past
        them) a batch is: the replies at or below what we hold come first and are
        compared with our framing (``retained_batch``)."""
        if reqnr <= self.retained_through:
            return reqnr not in self.retained
        return self.retained_came < self.retained_due

    def adopted_from(self) -> int:
        """InvokeRequest.adopted_from_reqnr: the first request we answered from the
        retained replies that no drone call of ours carried yet (0: none).

        Carried until the drone answers a call that carried it, in whichever
        mastership of ours that is: the adopting mastership's calls may all be refused
        (a handover overtook them), and the drone would count those replies as brought
        by the master that lost them, older than a give-up of that master's the ring
        may hold. Our later mastership frames them as we adopted them (a rejoin would
        have dropped our framing and this core with it)."""
        return self.adopted

    def connect_request(self) -> drone_pb2.ConnectRequest:
        """The Connect we send now, read at every (re)connect: the epoch of the mastership
        whose log we may hold alone (the drone fences us if a takeover gave it up), the
        request number that log holds up to, a mastership an earlier self gave up
        (its fresh self is granted a new epoch), and the log message we handled last
        (a taker's own follow it)."""
        p = self.protocol
        return drone_pb2.ConnectRequest(
            controller_id=p.id,
            mastership_epoch=p.log_mastership_epoch,
            holds_reqnr=p.held_reqnr,
            given_up_epoch=p.given_up_epoch,
            holds_lognr=p.lognr,
            holds_lognr_epoch=p.epoch_of(p.lognr) if p.lognr else 0,
        )

    def carried(self, preparation: drone_pb2.PreparationProgress | None) -> drone_pb2.InvokeRequest:
        """What a drone call carries beside the request (InvokeRequest's fields): the
        watermark the drone must not go below, the answers we gave the program ourselves
        since our last drone call (the drone keeps them for a taker), the first request of
        this mastership answered from the retained replies, and a prepared handover's
        ``preparation`` progress."""
        framed_after = self.protocol.framed_after
        carried = drone_pb2.InvokeRequest(
            watermark_reqnr=self.protocol.watermark_reqnr,
            master_answers=[to_retained(entry) for entry in self.answered_here],
            preparation=preparation,
            adopted_from_reqnr=self.adopted_from(),
        )
        if framed_after is not None:
            carried.framed_after_lognr, carried.framed_after_epoch = framed_after
        return carried

    def _adopt(self, reqnr: int) -> None:
        if not self.adopted:
            self.adopted = reqnr

    def _log(self, entry: ring_pb2.LogEntry) -> list[CoreEffect]:
        """The master logs ``entry`` as the program's answer."""
        effects = self.protocol.on_reply(entry)
        return [self.consume(entry), *effects]

    def _from_retained(
        self, kept: drone_pb2.RetainedReply, method: str, request: bytes
    ) -> ring_pb2.LogEntry | Fail:
        try:
            return from_retained(kept, method, request)
        except StatusError as err:
            return Fail(f"controller {self.protocol.id}: {err.message}", err.code)

    def _replay(
        self, method: str, request: bytes
    ) -> tuple[ring_pb2.LogEntry | None, list[CoreEffect]]:
        """The log's entry for the call (REPLAY); None and a Fail if it is another call."""
        more = len(self.protocol.log) > 1  # REPLAY goes on after this entry
        try:
            entry, effects = self.protocol.replay(method, request)
        except NonDeterminismError as exc:
            text = f"controller {self.protocol.id}: {exc}"
            return None, [Fail(text, grpc.StatusCode.FAILED_PRECONDITION)]
        return entry, [self.consume(entry, more), *effects]

    def _again(
        self, entry: ring_pb2.LogEntry, method: str, code: grpc.StatusCode
    ) -> list[CoreEffect]:
        """A give-up the entry contradicts: the program starts again (``ReplayAgain``)."""
        return [*self.protocol.restart_program(), ReplayAgain(entry, method, code), *self.rejoin()]

    def settle(self) -> tuple[bool, list[CoreEffect]]:
        """Gives the log's entry to each call the program gave up on while this controller
        waited, in order: True once none is left; False to wait for a change (or the
        mission stopped: a ``Fail``, or the program starts again: ``ReplayAgain``).

        The program's next call must not take the entry of one it gave up on. The
        entry comes from the log (REPLAY), or, master meanwhile: after the drone's
        grant of the mastership, the reply the drone retains for it if a lost
        master's program acted on it (the drone served it a later request), else
        our give-up, logged. An entry that is not that give-up makes the program
        start again. Nothing while this controller rejoins: its program is to start
        again from the log.
        """
        p, effects = self.protocol, list[CoreEffect]()
        if self.rejoining:
            return not self.abandoned, effects
        while self.abandoned:
            method, request, code = self.abandoned[0]
            if p.state is State.REPLAY:
                entry, replayed = self._replay(method, request)
                effects += replayed
                if entry is None:
                    return False, effects
                self.abandoned.popleft()
                if entry.status_code != code.value[0]:
                    return False, [*effects, *self._again(entry, method, code)]
            elif p.state is State.ACTIVE and p.granted_epoch != p.epoch:
                return False, effects  # the drone's grant may bring a retained answer
            elif p.state is State.ACTIVE and p.reqnr + 1 < self.retained_through:
                # The drone retains the answer to this request, and a lost master's
                # program acted on it: that is the entry, not our program's give-up.
                # The last one retained no program acted on: our give-up is logged.
                reqnr = p.reqnr + 1
                if self.retained_pending(reqnr):
                    return False, effects
                entry_or_fail = self._from_retained(self.retained.pop(reqnr), method, request)
                if isinstance(entry_or_fail, Fail):
                    return False, [*effects, entry_or_fail]
                self._adopt(reqnr)
                self.abandoned.popleft()
                effects += self._log(entry_or_fail)
                if entry_or_fail.status_code != code.value[0]:
                    return False, [*effects, *self._again(entry_or_fail, method, code)]
            elif p.state is State.ACTIVE:
                self.abandoned.popleft()
                reqnr = p.reqnr + 1
                self.retained.pop(reqnr, None)
                effects += self._log(given_up_entry(reqnr, method, request, code))
            else:
                return False, effects
        return True, effects

    def answer(self, method: str, request: bytes) -> tuple[CallStep, list[CoreEffect]]:
        """What to do with the program's call now (Algorithm 1 with the drone's word):
        REPLAY answers from the log; PASSIVE holds it; ACTIVE answers it from the
        replies the drone retains for a taker, or asks the Clock or the drone.
        An ACTIVE master's Clock call waits for the drone's grant of the mastership
        (the drone may retain a lost master's Clock answer for it), and any call
        for the retained replies still to come."""
        p = self.protocol
        if self.rejoining:
            # What the program would take now may be the framing the rejoin drops; its
            # fresh self answers it.
            return Hold(), []
        if p.state is State.REPLAY:
            kept = self.retained.get(p.reqnr + 1)
            if kept is not None and (refused := self._refuse_replaced([kept])):
                # A taker that held less than the replies the drone retains for it was
                # given by the ring a framing of one that a later takeover replaced:
                # refused as when the grant's retained replies find it.
                return Hold(), refused
            entry, replayed = self._replay(method, request)
            return (Answer(entry) if entry is not None else Hold()), replayed
        if p.state is not State.ACTIVE:
            return Hold(), []
        reqnr = p.reqnr + 1
        if method.startswith(CLOCK_SERVICE) and p.granted_epoch != p.epoch:
            return Hold(reqnr), []
        if self.retained_pending(reqnr):
            return Hold(reqnr), []
        effects: list[CoreEffect] = []
        if self.first_new_call_due and reqnr > self.retained_through:
            self.first_new_call_due = False
            effects.append(FirstNewCall(reqnr, method, p.epoch))
        kept = self.retained.pop(reqnr, None)
        if kept is not None:
            entry_or_fail = self._from_retained(kept, method, request)
            if isinstance(entry_or_fail, Fail):
                return Hold(reqnr), [*effects, entry_or_fail]
            self._adopt(reqnr)
            self.answered_from_retained += 1
            fields = {"reqnr": reqnr, "method": method}
            effects.append(Note("info", "answered from the retained tail", fields))
            return Answer(entry_or_fail), [*effects, *self._log(entry_or_fail)]
        digest = request_digest(method, request)
        refusal = self._clock_refusal(method, request)
        if refusal is not None:  # logged as the call's outcome, as a drone's failure is
            entry = ring_pb2.LogEntry(
                reqnr=reqnr,
                method=method,
                request_digest=digest,
                request=request,
                status_code=refusal.code.value[0],
                status_message=refusal.message,
            )
            return Answer(entry), [*effects, *self._log(entry)]
        if method in (CLOCK_NOW, CLOCK_SLEEP):
            return AskClock(reqnr, digest), effects
        # Every attempt of the call carries this watermark or a higher one (``carried``).
        self.asked_with = (reqnr, p.watermark_reqnr)
        return AskDrone(reqnr, digest), effects

    def _clock_refusal(self, method: str, request: bytes) -> StatusError | None:
        """A Sleep beyond the mission's bound (``safety.sleep_refusal``), else None."""
        if method != CLOCK_SLEEP:
            return None
        return sleep_refusal(api.SleepRequest.FromString(request).seconds, self.max_sleep_s)

    def logged(
        self, reqnr: int, entry: ring_pb2.LogEntry
    ) -> tuple[ring_pb2.LogEntry | None, list[CoreEffect]]:
        """The answer to request ``reqnr`` came (the Clock's or the drone's): logged if
        still ours to log; None if a handover notice overtook it (footnote 2: the new
        master re-sends the request, the drone answers it from its cache, and the
        program still sees this reply)."""
        if not self.ours_to_log(reqnr):
            return None, [
                Note("info", "reply discarded after handover", {"discarded_reqnr": reqnr})
            ]
        if entry.drone_epoch and self.asked_with[0] == reqnr:  # the drone's own reply
            self.protocol.drone_took_watermark(self.asked_with[1])
            if self.adopted and self.adopted < reqnr:
                self.adopted = 0  # carried by this call (``adopted_from``)
        return entry, self._log(entry)

    def gave_up(
        self, reqnr: int, method: str, request: bytes, code: grpc.StatusCode
    ) -> list[CoreEffect]:
        """The program gave up (``code``) on its call: on request ``reqnr`` of an ACTIVE
        master at it (0: while held). The master logs the give-up as the call's outcome
        (it is what the program saw, so every replica's program sees it, and a new
        master answers it from the log) if it is still its to log, the drone granted
        the mastership, and no retained reply answers it. Otherwise the call is
        settled like one given up while waiting (``settle``): a handover overtook it,
        or the drone retains (or may: no grant yet) the answer a lost master's program
        had."""
        p = self.protocol
        if (
            reqnr
            and self.ours_to_log(reqnr)
            and p.granted_epoch == p.epoch
            and reqnr >= self.retained_through
        ):
            self.retained.pop(reqnr, None)
            note = Note(
                "warning",
                "the mission program gave up on a call",
                {"reqnr": reqnr, "code": code.name},
            )
            return [note, *self._log(given_up_entry(reqnr, method, request, code))]
        self.abandoned.append((method, request, code))
        return []

    # -- timers ------------------------------------------------------------------------

    def _arm(self, now: float, drone_connected: bool, out: list[CoreEffect]) -> None:
        """The deadlines the state makes due, against those armed: an ``Arm`` for each new
        or moved one, a ``Disarm`` for each moot one.

        - A gap is noted when it opens (another message missing, another gap), and
          its repair armed ``repair_s`` later; a gap that fills disarms it.
        - A route held back is decided again as soon as the hold ends (no longer
          ACTIVE, or the drone's Connect stream up): nothing else ends it.
        - A preparation's end stays armed while it is under way.
        """
        p = self.protocol
        missing = p.missing_lognr
        if missing is None:
            self.gap = None
        elif self.gap is None or self.gap[0] != missing:
            self.gap = (missing, now, now + self.repair_s)
        if self.route_held and (p.state is not State.ACTIVE or drone_connected):
            self.route_held = False
            self.route_at = now
        preparing = self.prepared is not None and p.preparing_for is not None
        deadlines = (
            None if self.gap is None else self.gap[2],
            self.route_at,
            self.prepare_until if preparing else None,
        )
        if deadlines == self._deadlines:
            return  # most steps: nothing moved
        self._deadlines = deadlines
        for timer, at in zip(TIMERS, deadlines, strict=True):
            if at is None:
                if self.armed.pop(timer, None) is not None:
                    out.append(Disarm(timer))
            elif self.armed.get(timer) != at:
                self.armed[timer] = at
                out.append(Arm(timer, at))

    def timer_fired(self, timer: Timer, now: float, sight: RingSight) -> list[CoreEffect]:
        """The deadline armed for ``timer`` came (the driver fires only the one armed
        last): the decision it was armed for, with what the driver sees now. A timer
        fires at its deadline, never before: a runtime's loop may run it up to its
        clock's resolution early."""
        at = self.armed.pop(timer, None)
        if at is None:
            return []
        self._deadlines = None  # ``armed`` changed: the next step compares it whole
        now = max(now, at)
        if timer is Timer.GAP:
            missing = self.protocol.missing_lognr
            frames = None if missing is None else sight.frames_at.get(missing)
            return self.gap_due(now, self.repair_s, frames)
        if timer is Timer.ROUTE:
            return self.route(now, sight)
        prepared, self.prepared = self.prepared, None
        if prepared is None:
            return []
        return self.preparation_over(*prepared, self.prepare_until)

    def ring_changed(self, now: float, sight: RingSight) -> list[CoreEffect]:
        """A ring stream came up, went down or was opened: the route decided now, and
        armed for when a stream down reaches the detection time (``route``)."""
        return self.route(now, sight)

    def route(self, now: float, sight: RingSight) -> list[CoreEffect]:
        """Where the ring's messages go now (``route_due``), and when that may change by
        itself: the first moment a stream down now has been down for the detection
        time (``Timer.ROUTE``). A stream counts as down for it from that moment on,
        as the timer is armed."""
        self.route_held = False
        self.route_at = None
        detection_s = self.detection_s
        if detection_s <= 0 or len(self.protocol.ring) < 3:
            return []
        down_since = sight.down_since

        def down_for(pid: int) -> float | None:
            since = down_since.get(pid)
            if since is None:
                return None
            return detection_s if now >= since + detection_s else now - since

        effects = self.route_due(down_for, detection_s, sight.drone_connected)
        later = [since + detection_s for since in down_since.values() if since + detection_s > now]
        self.route_at = min(later, default=None)
        return effects

    def gap_due(
        self, now: float, repair_s: float, frames_seen_at: float | None = None
    ) -> list[CoreEffect]:
        """A log message missing for ``repair_s`` while later ones are queued (or our
        handover message did not come back): our predecessors re-send from our hello
        (``RepairGap``); again, twice as late each time (at most ``GAP_REPAIR_MAX_S``),
        if the gap stays. A taker whose gap stayed after a repair gives it up and goes
        ACTIVE (``ControllerProtocol.give_up_gap``): the message died with the lost
        master. Not a gap while its frames are coming (``frames_seen_at`` within
        ``repair_s``: a large message over a slow link); re-opening the streams would
        only make it start again. Asked at any time; acts only when due (``gap``)."""
        p = self.protocol
        missing = p.missing_lognr
        if missing is None:
            self.gap = None
            return []
        if self.gap is None or self.gap[0] != missing:
            self.gap = (missing, now, now + repair_s)
            return []
        if frames_seen_at is not None and now - frames_seen_at < repair_s:
            self.gap = (missing, now, now + repair_s)
            return []
        lognr, since, due = self.gap
        if now < due:
            return []
        if now - since >= 2 * repair_s:  # a repair was tried, and the gap stayed
            given_up = p.give_up_gap()
            if given_up:
                self.gap = None
                note = Note(
                    "warning",
                    "taker gives up log messages queued beyond a gap the repair did not "
                    "fill; framing those replies from the drone's",
                    {"missing_lognr": lognr, "missing_for_s": round(now - since, 3)},
                )
                return [note, *given_up]
        self.gap = (lognr, since, now + min(2 * (now - since), GAP_REPAIR_MAX_S))
        note = Note(
            "warning",
            "log message missing while later ones are queued (or our handover message did "
            "not come back); predecessors re-send from our hello",
            {
                "missing_lognr": lognr,
                "missing_for_s": round(now - since, 3),
                "queued": len(p.log_queue),
            },
        )
        return [note, RepairGap()]

    def route_due(
        self,
        down_for: Callable[[int], float | None],
        detection_s: float,
        drone_connected: bool,
    ) -> list[CoreEffect]:
        """Where the ring's messages go: the first controller after us whose stream has
        not been down for ``detection_s`` (``ring_route``; ``down_for`` says how long
        each has been, None if never tried); back to the natural successor as soon as
        its stream is up again. Not around a successor while we are an ACTIVE master
        cut off from the drone (``ControllerProtocol.may_route_around``): asked again."""
        p = self.protocol
        if detection_s <= 0 or len(p.ring) < 3:
            return []  # with two controllers the only other one is the master or nobody
        chosen, skipped = ring_route(p.ring, p.id, down_for, detection_s, p.successor)
        if chosen == p.successor:
            return []
        if not p.may_route_around(skipped, self.routed_around, drone_connected):
            self.route_held = True
            return []
        natural = p.ring[(p.ring.index(p.id) + 1) % len(p.ring)]
        if chosen == natural:
            note = Note("info", "ring successor back; ring restored", {"successor": chosen})
        else:
            fields = {"unreachable": skipped, "successor": chosen, "detection_s": detection_s}
            note = Note("warning", "ring successor unreachable; routing around it", fields)
        previous = p.successor
        p.route_to(chosen)
        self.routed_around = skipped
        return [note, RouteTo(chosen, skipped, previous, natural)]
