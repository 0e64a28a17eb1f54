"""Known defects of issue 9, put back one at a time by patching the running code.

Each mutation replaces a function (or a constant) of the code the
simulation runs for the duration of a ``with mutated(name):`` block and
restores it afterwards; no file is edited. The patches go to the shipped
pure cores (``ControllerProtocol``, ``DroneCore``, ``Sequencer``,
``ReplyCache``), except where the defect lived in a driver's I/O (a caller's
cancellation, a ring link's re-send), which the docstring says.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from baton import authenticity
from baton.authenticity import Keys, Verifier
from baton.controller import call_flow
from baton.controller import core as core_module
from baton.controller.core import ControllerCore, CoreEffect
from baton.controller.link_core import Greeting, LinkCore, SyncWord
from baton.controller.protocol import ConnectDrone, ControllerProtocol, Effect, Refusal, State
from baton.controller.sync_words import Belief
from baton.drone import core as drone_core
from baton.drone import sequencer
from baton.drone.core import DroneCore
from baton.drone.dedupe import ReplyCache
from baton.drone.operator import Operator
from baton.drone.request_flow import Begin, Booking, Execute, RequestFlow
from baton.rpc.errors import StatusError
from baton.sim.drone import Request, SimDrone
from baton.v1 import drone_pb2, ring_pb2

MUTATIONS: dict[str, Mutation] = {}


@dataclass(frozen=True)
class Mutation:
    """A defect: what it was, and the patches that put it back."""

    name: str
    defect: str
    patches: Callable[[], list[tuple[Any, str, Any]]]
    # SimOptions fields the defect needs to matter (e.g. the lose-master scenario).
    options: dict[str, Any] = field(default_factory=dict)


@contextlib.contextmanager
def mutated(name: str | None) -> Iterator[None]:
    """Applies mutation ``name`` (None: nothing) for the block."""
    if name is None:
        yield
        return
    saved = []
    for target, attribute, value in MUTATIONS[name].patches():
        saved.append((target, attribute, getattr(target, attribute)))
        setattr(target, attribute, value)
    try:
        yield
    finally:
        for target, attribute, value in reversed(saved):
            setattr(target, attribute, value)


def _line44() -> list[tuple[Any, str, Any]]:
    """Algorithm 1, line 44: a message in order arriving during REPLAY is dropped, not queued."""
    original = ControllerProtocol.on_log

    def on_log(self: ControllerProtocol, message: ring_pb2.LogMessage) -> list[Effect]:
        drop = (
            self.state is State.REPLAY
            and message.lognr == self.lognr + 1
            and message.lognr not in self._received
        )
        effects = original(self, message)
        if drop:
            self.log_queue.pop(message.lognr, None)
        return effects

    return [(ControllerProtocol, "on_log", on_log)]


def _defect1() -> list[tuple[Any, str, Any]]:
    """Issue 9, defect 1: a caller that goes away cancels the execution; nothing is booked.

    A driver's I/O, not a decision: drone/service.py's handler was not
    shielded, so a gRPC cancellation (a deadline, a dropped connection)
    cancelled the vehicle call and the bookkeeping with it (patched in the
    simulation's driver, ``SimDrone._caller_gone``).
    """

    def caller_gone(self: SimDrone, request: Request) -> None:
        if request in self.queue:
            self.queue.remove(request)
        elif self.busy is not None and self.busy.request is request:
            self.busy, self.intent = None, None
            self.world.loop.after(0.0, self._next)

    return [(SimDrone, "_caller_gone", caller_gone)]


def _defect2() -> list[tuple[Any, str, Any]]:
    """Issue 9, defect 2: UNAVAILABLE (the vehicle not connected) is booked as the outcome.

    ``DroneCore.books``.
    """

    def books(error: StatusError) -> bool:
        return True

    return [(DroneCore, "books", staticmethod(books))]


def _defect3_active() -> list[tuple[Any, str, Any]]:
    """Issue 9, defect 3: the configured initial master starts ACTIVE on its own word.

    As protocol.py did before epochs: a restarted initial master came up
    ACTIVE with reqnr 0 (the simulation's initial master is ring[0]).
    """
    original = ControllerProtocol.start

    def start(self: ControllerProtocol) -> list[Effect]:
        if self.id == self.ring[0]:
            self.state, self.master, self.catch_up_to = State.ACTIVE, True, 0
            return [ConnectDrone()]
        return original(self)

    return [(ControllerProtocol, "start", start)]


def _defect3_resend() -> list[tuple[Any, str, Any]]:
    """Issue 9, defect 3: a predecessor re-sends a restarted successor only others' messages.

    As ring.py did: the successor's own messages stopped at the predecessor
    and were never given back. Patched in the shipped ``LinkCore.connected``,
    the greeting both links write.
    """
    original = LinkCore.connected

    def connected(
        self: LinkCore,
        hello: int,
        epoch: int,
        word: tuple[int, int],
        proof: ring_pb2.MasterWord | None = None,
    ) -> Greeting:
        greeting = original(self, hello, epoch, word, proof)
        history = self.history
        if history is None:
            return greeting
        others = [n for n in greeting.from_history if history.get(n).origin != self.peer]
        return Greeting(greeting.sync, others)

    return [(LinkCore, "connected", connected)]


def _defect4() -> list[tuple[Any, str, Any]]:
    """Issue 9, defect 4: refusals not judged by epoch; any refusal naming us is DISAGREE."""

    def judge_refusal(
        self: ControllerProtocol, sent_epoch: int, master: int, epoch: int
    ) -> Refusal:
        return Refusal.HANDED_OVER if master != self.id else Refusal.DISAGREE

    return [(ControllerProtocol, "judge_refusal", judge_refusal)]


def _defect5() -> list[tuple[Any, str, Any]]:
    """Issue 9, defect 5: no bound on how far a new reqnr may jump."""
    return [(sequencer, "MAX_REQNR_GAP", 2**80)]


def _defect10() -> list[tuple[Any, str, Any]]:
    """Issue 9, defect 10: a restarted drone service starts as a new drone.

    ``DroneCore.resume`` and ``DroneCore.cut_off``: nothing was stored, so master,
    epoch, reply cache and the request cut off were gone.
    """

    def resume(self: DroneCore, *args: object) -> None:
        return None

    def cut_off(self: DroneCore, intent: object) -> None:
        return None

    return [(DroneCore, "resume", resume), (DroneCore, "cut_off", cut_off)]


def _forgets_tail() -> list[tuple[Any, str, Any]]:
    """Issue 10: the drone forgets the retained tail: the reply cache evicts beyond its
    window whatever the watermark (dedupe.py ReplyCache._evict), so a taker that re-sends
    what the lost master never flushed finds the replies gone."""

    def evict(self: ReplyCache) -> None:
        while len(self._entries) > self.window:
            del self._entries[next(iter(self._entries))]

    return [(ReplyCache, "_evict", evict)]


def _no_fencing() -> list[tuple[Any, str, Any]]:
    """Issue 10: no fencing: a master whose role was taken over takes the takeover notice
    (or refusal) for a cooperative handover: it sends its unflushed log to the taker and
    stays a replica with everything it held, instead of ``on_fenced`` and a rejoin with
    nothing (``ControllerCore.fenced``, the core of node.py and the simulation)."""

    def fenced(
        self: ControllerCore,
        new_master: int,
        epoch: int,
        watermark: int = 0,
        taker_holds: tuple[int, int] = (0, 0),
    ) -> list[CoreEffect]:
        if self.protocol.state is not State.ACTIVE:
            return []
        return self.handover_notice(new_master, 0, epoch)

    return [(ControllerCore, "fenced", fenced)]


def _flies_on_in_failsafe() -> list[tuple[Any, str, Any]]:
    """Issue 32: a vehicle in failsafe silently flies on: the mission's next call is
    executed instead of refused (``DroneCore.refusal`` ignores the failsafe)."""
    original = DroneCore.refusal

    def refusal(self: DroneCore, method: str, payload: bytes) -> StatusError | None:
        failsafe, self.failsafe = self.failsafe, None
        try:
            return original(self, method, payload)
        finally:
            self.failsafe = failsafe

    return [(DroneCore, "refusal", refusal)]


def _flies_on_while_paused() -> list[tuple[Any, str, Any]]:
    """Issue 32: an operator's pause holds nothing back: the master's next request is
    admitted and executed at once (``DroneCore.holds`` never says wait)."""

    def holds(self: DroneCore, request: drone_pb2.InvokeRequest) -> bool:
        return False

    return [(DroneCore, "holds", holds)]


def _flies_on_after_abort() -> list[tuple[Any, str, Any]]:
    """Issue 32: an abort ends nothing: the mission's next call is executed instead of
    refused (``Operator.refusal`` ignores the end)."""

    def refusal(self: Operator, method: str) -> StatusError | None:
        return None

    return [(Operator, "refusal", refusal)]


def _forgets_it_flew() -> list[tuple[Any, str, Any]]:
    """Issue 32: a restarted drone forgets that the vehicle was in the air when it stopped
    (``DroneCore.restore_command`` drops the state file's ``airborne``), so a vehicle the
    autopilot's GCS failsafe landed meanwhile is flown on, not put in the autopilot
    failsafe (``safety.landed_while_down``)."""
    original = DroneCore.restore_command

    def restore_command(self: DroneCore, kept: Any, now: float) -> None:
        original(self, kept, now)
        self.airborne_before_restart = False

    return [(DroneCore, "restore_command", restore_command)]


def _pictures_unplaced() -> list[tuple[Any, str, Any]]:
    """A picture needs nothing of the vehicle (``core.needs_vehicle``: Mobility only), so
    one sent while the vehicle's link is out, or to a drone restarted before its first
    look, is taken where the vehicle's place is unknown."""
    return [(drone_core, "needs_vehicle", lambda route: route.service == "Mobility")]


def _believes_unbacked_claims() -> list[tuple[Any, str, Any]]:
    """Issue 33: a mastership a log message claims is believed without the drone's grant
    (``authenticity.unbacked_claim``, which ``ControllerCore.log_arrived`` asks, backs
    every claim)."""

    def unbacked_claim(drone: Verifier, message: ring_pb2.LogMessage, receiver: int) -> None:
        return None

    return [(authenticity, "unbacked_claim", unbacked_claim)]


def _believes_sync_words() -> list[tuple[Any, str, Any]]:
    """Issue 33: a sync frame's words believed as they were before they needed evidence
    (``sync_words.believe`` takes every word; the protocol moves the watermark, waits
    and rejoins on any)."""

    def believe(keys: Keys | None, word: SyncWord) -> Belief:
        return Belief(word, True)

    def credit(self: ControllerProtocol, holds_lognr: int, holds_epoch: int, proof: bytes) -> int:
        return holds_lognr

    def believes(self: ControllerProtocol, *args: object) -> bool:
        return True

    return [
        (core_module, "believe", believe),
        (ControllerProtocol, "_watermark_credit", credit),
        (ControllerProtocol, "_believes_newer", believes),
        (ControllerProtocol, "_believes_promise", believes),
    ]


def _intent_after_execution() -> list[tuple[Any, str, Any]]:
    """A request's intent stored only once the vehicle's turn is over (``RequestFlow.run``'s
    ``Begin`` held back until after ``Execute``): a drone restarted while the vehicle acts
    finds nothing cut off, and the re-sent request executes again."""
    original = RequestFlow.run

    def run(self: RequestFlow) -> Any:
        steps, held, result = original(self), None, None
        while True:
            try:
                io = steps.send(result)
            except StopIteration as stop:
                return stop.value
            if isinstance(io, Begin):
                held, result = io, None
                continue
            if isinstance(io, Booking) and held is not None:
                yield held
                held = None
            result = yield io
            if isinstance(io, Execute) and held is not None:
                yield held
                held = None

    return [(RequestFlow, "run", run)]


def _no_resend() -> list[tuple[Any, str, Any]]:
    """A drone call that found the drone unavailable is not sent again: its UNAVAILABLE is
    the call's outcome at once (``CallFlow`` asks ``invoking.failed`` with no time left),
    though nothing reached the vehicle and the number stays unused."""
    original = call_flow.failed

    def failed(core: ControllerCore, sent: Any, code: Any, *args: Any) -> Any:
        details, refusal, waited, _limit, attempts = args
        return original(core, sent, code, details, refusal, waited, 0.0, attempts)

    return [(call_flow, "failed", failed)]


LOSE_MASTER = {"lose_master": True}
FAILSAFE = {"failsafe": True}
OPERATOR = {"operator": True}
LYING = {"lying": True}
AUTOPILOT = {"autopilot": True}

for _mutation in (
    Mutation("line44", "Algorithm 1 line 44: in-order message dropped during REPLAY", _line44),
    Mutation("defect1", "drone books nothing when the caller goes away", _defect1),
    Mutation("defect2", "UNAVAILABLE cached as the request's outcome", _defect2),
    Mutation("defect3-active", "restarted initial master ACTIVE on its own word", _defect3_active),
    Mutation("defect3-resend", "predecessor re-sends only others' messages", _defect3_resend),
    Mutation("defect4", "refusals not judged by epoch", _defect4),
    Mutation("defect5", "no reqnr gap bound", _defect5),
    Mutation("defect10", "drone restart forgets its state", _defect10),
    Mutation(
        "forgets-tail", "drone evicts replies above the watermark", _forgets_tail, LOSE_MASTER
    ),
    Mutation(
        "no-fencing", "a fenced master hands over instead of rejoining", _no_fencing, LOSE_MASTER
    ),
    Mutation(
        "flies-on-in-failsafe",
        "a call after a failsafe executed without the operator's resume",
        _flies_on_in_failsafe,
        FAILSAFE,
    ),
    Mutation(
        "flies-on-while-paused",
        "a call of a paused mission executed at once",
        _flies_on_while_paused,
        OPERATOR,
    ),
    Mutation(
        "flies-on-after-abort",
        "a call after an abort executed",
        _flies_on_after_abort,
        OPERATOR,
    ),
    Mutation(
        "forgets-it-flew",
        "a restarted drone flies on a vehicle its GCS failsafe landed",
        _forgets_it_flew,
        AUTOPILOT,
    ),
    Mutation(
        "pictures-unplaced",
        "a picture taken while the vehicle's place is unknown",
        _pictures_unplaced,
    ),
    Mutation(
        "believes-unbacked-claims",
        "a mastership claimed without the drone's grant believed",
        _believes_unbacked_claims,
        LYING,
    ),
    Mutation("no-resend", "a drone call found unavailable failed, not sent again", _no_resend),
    Mutation(
        "intent-after-execution",
        "a request's intent stored after the vehicle acted",
        _intent_after_execution,
    ),
    Mutation(
        "believes-sync-words",
        "a sync frame's words believed without evidence",
        _believes_sync_words,
        LYING,
    ),
):
    MUTATIONS[_mutation.name] = _mutation
