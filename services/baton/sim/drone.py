"""The simulated drone: a driver of the real ``DroneCore``, as ``drone/service.py`` is.

``SimDrone`` keeps one line of execution (its queue: requests, Handover and
operator calls, the master's word, the watches' turns, policy steps, each
taken in arrival order, one at a time, as the service's lock takes them),
turns the simulated network's calls and streams into the core's events
(``handover_call``, ``master_watch``, ``preparation_word``,
``fresh_self_connect``, ``policy_handover``, ``restarted``,
``failsafe_check``, ``operator_command``) and applies the effects they
return (``_apply``, as ``DroneService.apply``); each request runs the same
``request_flow.RequestFlow`` as the service's ``Invocations``; a Connect
stream writes what ``connects.ConnectStream`` says. A restart builds a new
core from what the store keeps (``Kept``): not the pending notices nor a
preparation; a command cut off by it is booked, a read runs again.

The vehicle and the camera are the ground truth (``sim/vehicle.py``); the
vehicle keeps the autopilot's own GCS failsafe: a drone service dead longer
than ``World.autopilot_gcs_timeout`` finds it returned or landed when it
restarts (``SimVehicle.gcs_failsafe``), and reads that through the same core
calls as the service (``DroneCore.restarted``, ``failsafe_check``).
Simplifications: a request takes a drawn time to execute, and a command
reaches the vehicle at a drawn point inside it (a drone restart before
that point means the vehicle never saw it); the vehicle's own
retransmission handling (``sim_vehicle/retransmissions.py``) is not
modelled; GetStatus, the fence and the station landing (no position) and
the operator's word on the Connect stream are not modelled.
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import grpc

from baton.authenticity import signed_reply
from baton.drone.connects import ConnectStream
from baton.drone.core import WATCH_TICK_S, DroneCore, Kept
from baton.drone.dedupe import CachedReply
from baton.drone.effects import (
    Abandon,
    Book,
    DroneEffect,
    Note,
    Preparing,
    Switched,
    TellTakeOver,
    pins_policy,
)
from baton.drone.invariants import DroneWatch
from baton.drone.invocations import answered_again
from baton.drone.operator import Operator
from baton.drone.policy import Decision
from baton.drone.request_flow import (
    Acknowledged,
    Begin,
    Booking,
    Duplicate,
    Execute,
    Executed,
    Failed,
    LookAtVehicle,
    Now,
    Outcome,
    Parked,
    Parse,
    RequestFlow,
    Send,
    VehicleSeen,
)
from baton.drone.request_flow import Flow as RequestSteps
from baton.drone.safety import (
    Failsafe,
    ModeSeen,
    commanded_action,
)
from baton.drone.sequencer import PREPARE_TIMEOUT_S, ScriptedHandover, Sequencer
from baton.drone.sight import DroneSight
from baton.drone.store import DroneState, Intent, counters_of
from baton.rpc.errors import StatusError
from baton.rpc.labels import label
from baton.rpc.methods import drone_api, service_prefix
from baton.sim.mission import UNPARSABLE
from baton.sim.policy_runner import PolicyStep, SimPolicyRunner
from baton.sim.vehicle import SimCamera, SimVehicle
from baton.v1 import drone_pb2

if TYPE_CHECKING:
    from baton.sim.controller import SimController
    from baton.sim.network import DroneLink
    from baton.sim.world import World

ROUTES = drone_api()
CAMERA = service_prefix("Camera")
# The sim's replies are tens of bytes: batches of about one or two of them, so that a
# stream can break between the Connected event and its last retained batch.
RETAINED_BATCH_BYTES = 64
POLICY = drone_pb2.HANDOVER_TRIGGER_POLICY


@dataclass(eq=False)
class Request:
    """An Invoke as it reaches the drone; ``link``/``connection`` say where its reply goes."""

    controller_id: int
    epoch: int
    reqnr: int
    method: str
    payload: bytes
    call_id: int
    link: DroneLink | None
    connection: int
    received_at: float = 0.0
    # What the request carries beside itself (``ControllerCore.carried``).
    carried: drone_pb2.InvokeRequest | None = None
    # For the oracles: the sender's incarnation, and how many calls its program
    # had consumed when it sent this (the drone acting on it depends on them).
    sender: SimController | None = None
    consumed: int = 0

    def proto(self) -> drone_pb2.InvokeRequest:
        """The InvokeRequest these fields are (what ``DroneCore.admit`` reads)."""
        request = drone_pb2.InvokeRequest(
            controller_id=self.controller_id,
            epoch=self.epoch,
            reqnr=self.reqnr,
            method=self.method,
            payload=self.payload,
        )
        if self.carried is not None:
            request.MergeFrom(self.carried)
        return request


@dataclass(frozen=True)
class HandoverOrder:
    """A Handover call (an operator's or a test's): it takes the lock like a request."""

    new_master: int
    prepared: bool = False  # HandoverRequest.prepared


@dataclass(frozen=True)
class PreparationWord:
    """A ReportPreparation call: the master's word between requests, under the lock."""

    controller_id: int
    epoch: int
    progress: drone_pb2.PreparationProgress


@dataclass(frozen=True)
class MasterCheck:
    """``watch_master``'s turn under the execution lock (``DroneCore.master_watch``)."""


@dataclass(frozen=True)
class FreshSelfConnect:
    """A Connect from a fresh self of the master that gave its mastership up
    (``Sequencer.fresh_self_due``): it takes the execution lock first."""

    link: DroneLink
    session: int
    connection: int
    request: drone_pb2.ConnectRequest


@dataclass(frozen=True)
class FailsafeCheck:
    """FailsafeWatch.run under the lock: the failsafe due checked again, then entered."""


@dataclass(frozen=True)
class OperatorOrder:
    """An operator's command (Drone.Pause, Resume, Abort, LandNow): takes the lock, then
    asks the core (operator_service.OperatorCommands)."""

    command: str  # operator.COMMANDS
    action: str = ""  # an abort's: rtl or land


@dataclass(eq=False)
class Execution:
    """A request under the execution lock (``request_flow.RequestFlow``), and where its
    flow is: executing on the vehicle from ``Send`` until ``ends_at``."""

    request: Request
    steps: RequestSteps
    admitted: bool = False
    reply: bytes = b""
    error: StatusError | None = None
    # The vehicle's link was up when the execution began (where a picture reads its place).
    vehicle_known: bool = True
    ends_at: float = 0.0


@dataclass(eq=False)
class Stream:
    """One open Connect stream (``master.MasterStream``)."""

    controller_id: int
    session: int
    link: DroneLink
    connection: int
    # What it already said (connects.ConnectStream).
    said: ConnectStream


@dataclass
class DroneStats:
    """What the oracles and the report read besides the ground truth."""

    epochs: DroneWatch = field(default_factory=DroneWatch)
    epoch_conflicts: list[str] = field(default_factory=list)
    cut_off: list[Intent] = field(default_factory=list)
    restarts: int = 0
    peak_cache: int = 0  # replies at or below the watermark (the window's)
    peak_retained: int = 0  # replies above it (kept for a takeover)


class SimDrone:
    """The drone service's decisions over simulated time (``drone/service.py``)."""

    def __init__(
        self,
        world: World,
        controllers: list[int],
        initial_master: int,
        script: dict[int, ScriptedHandover],
        cache_window: int,
        p_ack_lost: float,
        prepare_timeout_s: float = PREPARE_TIMEOUT_S,
    ) -> None:
        self.world = world
        self.controllers = list(controllers)
        self.initial_master = initial_master
        self.script = dict(script)
        self.cache_window = cache_window
        self.p_ack_lost = p_ack_lost
        self.prepare_timeout_s = prepare_timeout_s
        # Signs replies and grants (DroneService.signer); None without keys.
        self.signer = world.keys.drone if world.keys is not None else None
        self.core = DroneCore(self._sequencer(), world.takeover_after, world.safety)
        self.vehicle = SimVehicle(world.battery_drain, world.autopilot_gcs_timeout)
        self.camera = SimCamera()
        self.up = True
        # Durable (store.py): the request being executed, as its intent.
        self.intent: Intent | None = None
        # Volatile: gone at a restart.
        self.queue: deque[
            Request
            | HandoverOrder
            | MasterCheck
            | PreparationWord
            | PolicyStep
            | FreshSelfConnect
            | FailsafeCheck
            | OperatorOrder
        ] = deque()
        # Requests of a paused mission waiting for a resume, not admitted
        # (OperatorCommands.wait_resumed): their callers may still go away.
        self.parked: list[Request] = []
        self.waited = 0  # requests that waited for a resume, over every incarnation
        self.busy: Execution | None = None
        self.streams: dict[int, Stream] = {}
        self.stats = DroneStats()
        self.takeovers = 0
        self._watching = False
        self._check_queued = False
        self._failsafe_queued = False
        # Every prepared handover the drone carried out or forced (the record check).
        self.prepared_records: list[drone_pb2.HandoverRecord] = []
        self.preparations = 0  # begun
        self.words_moved = 0  # preparations ended by the master's word between requests
        # Prepared ones whose target in truth lacked more than the master's word said
        # (a diagnostic, not an oracle: docs/design.md, prepared handovers).
        self.understated: list[str] = []
        # The handover policy (--policy), volatile like the service's; and how its
        # handovers ended (``_switched``), over every incarnation of the service.
        self.policy = self._policy_runner()
        self.policy_switches: Counter[str] = Counter()
        self.policy_decided: Counter[str] = Counter()

    @property
    def seq(self) -> Sequencer:
        """The core's Sequencer (a restart makes a new core)."""
        return self.core.seq

    # -- requests -------------------------------------------------------------------

    def receive_invoke(self, request: Request) -> None:
        """An Invoke arrives; it waits for the lock (FIFO, as asyncio.Lock)."""
        request.received_at = self.world.loop.now
        self.queue.append(request)
        self._next()

    def handover_rpc(self, new_master: int, prepared: bool = False) -> None:
        """The Handover RPC: takes the lock, then switches (refused if already master), or
        begins a prepared handover (its caller is answered once the master moved; nobody
        waits for that here)."""
        if not self.up:
            return  # the operator's call fails UNAVAILABLE
        self.queue.append(HandoverOrder(new_master, prepared))
        self._next()

    def receive_report(self, cid: int, epoch: int, progress: drone_pb2.PreparationProgress) -> None:
        """ReportPreparation arrives; it waits for the lock like a request."""
        self.queue.append(PreparationWord(cid, epoch, progress))
        self._next()

    def _next(self) -> None:
        while self.up and self.busy is None and self.queue:
            item = self.queue.popleft()
            if isinstance(item, HandoverOrder):
                self._handover(item)
            elif isinstance(item, PreparationWord):
                now = self.world.loop.now
                moved = self.core.preparation_word(
                    item.controller_id, item.epoch, item.progress, now
                )
                self.words_moved += bool(moved)
                self._apply(moved, on_the_word=True)
            elif isinstance(item, PolicyStep):
                if self.policy is not None:
                    self.policy.carry_out(item)
            elif isinstance(item, MasterCheck):
                self._check_queued = False
                self._apply(self.sight().master_watch(self.core, self.world.loop.now))
            elif isinstance(item, FreshSelfConnect):
                self._fresh_self_connect(item)
            elif isinstance(item, FailsafeCheck):
                self._failsafe_queued = False
                self._failsafe_check()
            elif isinstance(item, OperatorOrder):
                self._operator(item)
            else:
                self._start(item)

    def _start(self, request: Request) -> None:
        """DroneService._invoke_to_the_end: the request's flow, up to the execution."""
        steps = RequestFlow(self.core, request.proto(), request.received_at).run()
        self._advance(Execution(request, steps), None)

    def _advance(self, execution: Execution, result: object) -> None:
        """Sends ``result`` to the request's flow and carries out what it yields, up to the
        vehicle's turn (``Invocations._perform``, on the virtual clock)."""
        request, now = execution.request, self.world.loop.now
        while True:
            try:
                io = execution.steps.send(result)
            except StatusError as err:  # refused at admission: nothing booked
                self._reply(request, None, err)
                return
            except StopIteration as stop:
                self._admitted(execution, stop.value)
                self._outcome(execution, stop.value)
                return
            self._admitted(execution, io)
            result = None
            if isinstance(io, Begin):
                self.intent = io.intent  # with what the admission keeps (store.begin)
            elif isinstance(io, Parse) and request.payload.startswith(UNPARSABLE):
                result = StatusError(
                    grpc.StatusCode.INVALID_ARGUMENT, f"payload of {request.method} does not parse"
                )
            elif isinstance(io, LookAtVehicle):
                result = VehicleSeen(self.vehicle.connected, "(an outage)")
            elif isinstance(io, Now):
                result = now
            elif isinstance(io, Send):
                self._executing(execution)
                return
            elif isinstance(io, Execute):
                self._act(execution, io.action)
                self.world.loop.at(execution.ends_at, self._complete, execution)
                return
            elif isinstance(io, Acknowledged) and self.policy is not None:
                self.policy.executed(ROUTES[request.method].name)  # the leg it flies
            elif isinstance(io, Booking):
                self._apply(io.effects)

    def _admitted(self, execution: Execution, turn: object) -> None:
        """Oracle 4's record, once the request passed admission (``_note_epoch``)."""
        if not execution.admitted and not isinstance(turn, Parked):
            execution.admitted = True
            request = execution.request
            self._note_epoch(request.controller_id, request.epoch, request.reqnr)

    def _executing(self, execution: Execution) -> None:
        """The request takes a drawn time to execute; its command reaches the vehicle at a
        drawn point inside it."""
        route, rng, now = ROUTES[execution.request.method], self.world.rng, self.world.loop.now
        if route.is_read:
            duration = rng.uniform(0.002, 0.02)
        elif route.service == "Camera":
            duration = rng.uniform(0.05, 0.3)
        else:
            duration = rng.uniform(0.02, 0.3)
        execution.vehicle_known, execution.ends_at = self.vehicle.connected, now + duration
        self.busy = execution
        self.world.loop.at(now + duration * rng.uniform(0.1, 0.9), self._reaches, execution)

    def _reaches(self, execution: Execution) -> None:
        if execution is self.busy:  # else the drone restarted first: the vehicle never saw it
            self._advance(execution, self.world.loop.now)

    def _act(self, execution: Execution, action: str | None) -> None:
        """The command reaches the vehicle (or the camera, or a read is answered)."""
        request, now = execution.request, self.world.loop.now
        if ROUTES[request.method].is_read:
            execution.reply = self.vehicle.read(now, request.reqnr, request.method)
        elif request.method.startswith(CAMERA):
            size = self.world.rng.randint(300, 3000)
            execution.reply = self.camera.take(
                now, request.reqnr, request.payload, size, execution.vehicle_known
            )
        else:
            execution.reply = self.vehicle.act(now, request.reqnr, request.method, request.payload)
            self.vehicle.obey(action)
            if self.p_ack_lost and self.world.rng.random() < self.p_ack_lost:
                execution.error = StatusError(
                    grpc.StatusCode.DEADLINE_EXCEEDED,
                    f"{request.method}: no acknowledgement from the vehicle; it may have acted",
                )

    def _complete(self, execution: Execution) -> None:
        if execution is self.busy:
            now = self.world.loop.now
            self._advance(execution, Executed(now, execution.reply, execution.error))

    def _outcome(self, execution: Execution, outcome: Outcome) -> None:
        """The caller's answer; the lock goes to the next in line."""
        request = execution.request
        if isinstance(outcome, Parked):
            self.parked.append(request)  # paused: waits for a resume, not admitted
            self.waited += 1
            return
        if not isinstance(outcome, Failed) or outcome.booked:
            _acted_on(request)
        if isinstance(outcome, Duplicate):
            self._answer_duplicate(request, outcome.cached)
        elif isinstance(outcome, Failed):
            self._reply(request, None, outcome.error)
        else:
            method, reqnr, digest = request.method, request.reqnr, outcome.digest
            reply = outcome.reply
            self._reply(
                request, signed_reply(self.signer, reqnr, outcome.epoch, method, digest, reply)
            )
        if execution is self.busy:
            self.busy = None
            self._next()

    def _apply(self, effects: list[DroneEffect], on_the_word: bool = False) -> None:
        """DroneService.apply: the core's effects in their order (``drone/effects.py``).
        The store is the core itself here (a restart copies it): a booked outcome only
        ends the request's intent. ``on_the_word``: the master's word moved it."""
        for effect in effects:
            if isinstance(effect, Abandon):
                self.intent = None  # store.abandon()
            elif isinstance(effect, Book):
                self.intent = None
                retained, _ = self.seq.cache.retained
                self.stats.peak_cache = max(self.stats.peak_cache, len(self.seq.cache) - retained)
                self.stats.peak_retained = max(self.stats.peak_retained, retained)
            elif isinstance(effect, Switched):
                self._switched(effect.record, on_the_word)
            elif isinstance(effect, Preparing):
                self._preparing(effect.notice)
            elif isinstance(effect, TellTakeOver):
                self._tell_take_over(effect.record.new_master, effect.take_over)
            elif isinstance(effect, Note):
                self.world.trace(f"drone: {effect.event} {dict(effect.fields)}")

    def _answer_duplicate(self, request: Request, cached: CachedReply) -> None:
        try:
            self._reply(request, answered_again(self.signer, request.reqnr, cached))
        except StatusError as err:
            self._reply(request, None, err)

    def _reply(
        self,
        request: Request,
        reply: drone_pb2.InvokeReply | None,
        error: StatusError | None = None,
    ) -> None:
        """The reply (or the error) on its way back to the caller; every failure counts as
        rejected (``Invocations.for_caller``)."""
        if error is not None:
            self.seq.rejected += 1
        link = request.link
        if link is None:
            return  # nobody waits for it (a garbled request)
        size = 0 if reply is None else len(reply.payload)
        link.to_controller(
            request.connection,
            size,
            link.owner.on_invoke_reply,
            request.call_id,
            reply,
            error,
            stream=False,
        )

    def _note_epoch(self, cid: int, epoch: int, reqnr: int) -> None:
        """Oracle 4's record: which controller the drone accepted requests from in each
        epoch (``DroneWatch.accepted``, the check a running drone makes too)."""
        problem = self.stats.epochs.accepted(epoch, cid, reqnr)
        if problem is not None:
            self.stats.epoch_conflicts.append(problem)

    # -- callers that go away ----------------------------------------------------

    def receive_cancel(self, call_id: int) -> None:
        """The caller cancelled its Invoke (a deadline, a program that gave up)."""
        for request in self._requests():
            if request.call_id == call_id:
                self._caller_gone(request)
                return
        # A request waiting for a resume: its wait ends with its call, nothing admitted.
        self.parked = [r for r in self.parked if r.call_id != call_id]

    def _requests(self) -> list[Request]:
        requests = [item for item in self.queue if isinstance(item, Request)]
        if self.busy is not None:
            requests.append(self.busy.request)
        return requests

    def _caller_gone(self, request: Request) -> None:
        """Nothing: DroneService.invoke runs the request in a task the caller cannot cancel.

        (Issue 9, defect 1: a received request runs to its end and is booked.)
        """

    # -- masters and streams -----------------------------------------------------

    def _handover(self, order: HandoverOrder) -> None:
        """DroneService.Handover under the lock (``DroneCore.handover_call``); a refusal is
        the operator's error, nothing changes."""
        try:
            connected = self.seq.master in self.streams
            now = self.world.loop.now
            self._apply(
                self.core.handover_call(order.new_master, order.prepared, False, connected, now)
            )
        except StatusError:
            return

    # -- the handover policy (drone/policy_runner.py; sim/policy_runner.py) ----------

    def _policy_runner(self) -> SimPolicyRunner | None:
        corridor = self.world.corridor
        return None if corridor is None else SimPolicyRunner(self, corridor)

    def queue_policy_step(self, step: PolicyStep) -> None:
        """The policy's decision waits for the execution lock like a request."""
        self.queue.append(step)
        self._next()

    def policy_handover(self, master: int, decision: Decision) -> str:
        """PolicyRunner.tick's handover under the lock: only if the master is still the one
        decided for; prepared if the master can prepare, else at once (a takeover if the
        decision says so). What it did, for the counts."""
        connected = self.seq.master in self.streams
        try:
            step, effects = self.core.policy_handover(
                decision, master, connected, self.world.loop.now
            )
        except StatusError as err:  # PolicyRunner.run: "policy step failed"
            self.world.trace(f"drone: policy step failed: {err.message}")
            return "failed"
        self._apply(effects)
        return step

    def _switched(self, record: drone_pb2.HandoverRecord, on_the_word: bool = False) -> None:
        """MasterStreams.wake: the old master's Connect handler resumes on a later loop turn;
        a master the script or an operator chose pins the policy (``effects.pins_policy``)."""
        if record.kind == drone_pb2.HANDOVER_KIND_TAKEOVER:
            self.takeovers += 1
        if self.policy is not None and pins_policy(record):
            self.policy.pin(record.new_master)
        if record.trigger == POLICY:
            self.policy_switches[_ending(record, on_the_word)] += 1
        prepared = ""
        if record.prepare_started_at:
            self.prepared_records.append(record)
            if record.kind == drone_pb2.HANDOVER_KIND_PREPARED:
                self._check_caught_up(record)
            prepared = (
                f", prepared for {record.decided_at - record.prepare_started_at:.3f}s, "
                f"lacked {record.prepare_lacked_bytes} B"
                + (", timed out" if record.prepare_timed_out else "")
            )
        trigger = label(drone_pb2.HandoverTrigger, record.trigger)
        kind = label(drone_pb2.HandoverKind, record.kind)
        self.world.trace(
            f"drone: master {record.old_master} -> {record.new_master} epoch {record.epoch} "
            f"after reqnr {record.after_reqnr} ({trigger}, {kind}{prepared})"
        )
        self.world.loop.after(0.0, self._wake, record.old_master)
        self.world.switched(record)  # where the lose-master fault may strike (faults.py)

    def _preparing(self, notice: drone_pb2.PrepareHandover) -> None:
        """A ``Preparing`` effect: wakes the master's stream to carry the notice."""
        self.preparations += 1
        self.world.trace(
            f"drone: preparing a handover from {self.seq.master} to {notice.target} "
            f"(epoch {notice.epoch}, timeout {notice.timeout_s:g}s)"
        )
        self.world.loop.after(0.0, self._wake, self.seq.master)
        self.watch()  # watch_master forces it at the deadline

    def _check_caught_up(self, record: drone_pb2.HandoverRecord) -> None:
        """Ground truth for a diagnostic, not an oracle: what the target lacks of the old
        master's log (history and unflushed entries) as the drone moves the master, more
        than the word (with the reply) said. The word speaks of the stream to the target
        only: a target restarted with nothing lacks the history too."""
        old = self.world.controller(record.old_master)
        target = self.world.controller(record.new_master)
        if not (old.alive and target.alive):
            return
        lacked = old.protocol.log.size + sum(
            old.history.get(n).ByteSize() for n in old.history.above(0) if n not in target.history
        )
        if lacked > record.prepare_lacked_bytes:
            what = (
                f"prepared handover {record.old_master}->{record.new_master} (epoch "
                f"{record.epoch}): the word said {record.prepare_lacked_bytes} B, the target "
                f"lacked {lacked} B (incarnation {target.incarnation})"
            )
            self.understated.append(what)
            self.world.trace(what)

    def _wake(self, cid: int) -> None:
        """The Connect handler's loop: the PrepareHandover to the master, if one is under
        way and not sent on this stream yet; the notice owed, then the stream ends."""
        stream = self.streams.get(cid)
        if stream is None or not self.up:
            return
        # The simulated controllers take no operator's word on the stream.
        for event in stream.said.woken(self.core, operator_words=False):
            if isinstance(event, drone_pb2.PrepareHandover):
                stream.link.to_controller(
                    stream.connection,
                    0,
                    stream.link.owner.on_drone_prepare,
                    stream.session,
                    event,
                    stream=True,
                )
            elif isinstance(event, drone_pb2.HandoverNotice):
                stream.link.to_controller(
                    stream.connection,
                    0,
                    stream.link.owner.on_drone_notice,
                    stream.session,
                    event,
                    stream=True,
                )
                self.core.delivered(cid, event)
                del self.streams[cid]

    def receive_connect(
        self, link: DroneLink, session: int, connection: int, request: drone_pb2.ConnectRequest
    ) -> None:
        """A Connect arrives; a fresh self of the master that gave its mastership up waits
        for the execution lock first (``FreshSelfConnect``)."""
        due = self.seq.fresh_self_due(
            request.controller_id, request.mastership_epoch, request.given_up_epoch
        )
        if due:
            self.queue.append(FreshSelfConnect(link, session, connection, request))
            self._next()
        else:
            self._attach(link, session, connection, request)

    def _attach(
        self, link: DroneLink, session: int, connection: int, request: drone_pb2.ConnectRequest
    ) -> None:
        """The Connect refused, or attached: Connected for the master, then the replies
        retained above what it holds; a notice owed."""
        cid = request.controller_id
        try:
            self.seq.admit_connect(cid, request.mastership_epoch)
        except StatusError as err:
            link.to_controller(
                connection, 0, link.owner.on_drone_refused, session, err, stream=True
            )
            return
        previous = self.streams.get(cid)
        if previous is not None:  # superseded: that stream ends
            previous.link.to_controller(
                previous.connection,
                0,
                previous.link.owner.on_drone_stream_ended,
                previous.session,
                stream=True,
            )
        said = ConnectStream(cid, self.signer)
        self.streams[cid] = Stream(cid, session, link, connection, said)
        grant, batches = said.opened(self.core, request, RETAINED_BATCH_BYTES)
        if grant is not None:  # Connected, then the replies retained above its holds
            owner = link.owner
            parts: list[tuple[int, Callable[..., None], tuple[Any, ...]]] = [
                (0, owner.on_drone_connected, (session, grant))
            ]
            parts += [
                (
                    sum(len(reply.reply) for reply in batch),
                    owner.on_drone_retained,
                    (session, batch),
                )
                for batch in batches
            ]
            link.stream_to_controller(connection, parts)
        self._wake(cid)

    def _fresh_self_connect(self, item: FreshSelfConnect) -> None:
        """DroneService.Connect under the lock: the takeover from the earlier self if it is
        still due, then the Connect as any other (a handler whose call ended meanwhile is
        gone)."""
        link, request = item.link, item.request
        if not link.owner.alive or link.generation != item.connection:
            return
        now = self.world.loop.now
        self._apply(
            self.core.fresh_self_connect(request.controller_id, request.given_up_epoch, now)
        )
        self._attach(link, item.session, item.connection, request)

    def receive_stream_closed(self, cid: int, session: int) -> None:
        """The controller closed its session's Connect stream."""
        stream = self.streams.get(cid)
        if stream is not None and stream.session == session:
            del self.streams[cid]

    def link_broke(self, cid: int, connection: int) -> None:
        """A controller's connection broke: its stream ends, its callers are gone."""
        stream = self.streams.get(cid)
        if stream is not None and stream.connection == connection:
            del self.streams[cid]
        self.core.seen(cid, self.world.loop.now)  # Standby's finally: seen as it went
        for request in self._requests():
            if request.controller_id == cid and request.connection == connection:
                self._caller_gone(request)
        self.parked = [
            r for r in self.parked if (r.controller_id, r.connection) != (cid, connection)
        ]

    # -- restarts ------------------------------------------------------------------

    def crash(self) -> None:
        """The drone service dies: calls in flight and streams are lost, the store stays."""
        self.world.trace(f"drone crashes (executing {self.intent})")
        self.up = False
        now = self.world.loop.now
        due = self.vehicle.gcs_silent(now)
        if due is not None:  # the autopilot's own GCS failsafe, if the silence lasts
            self.world.loop.at(due, self._gcs_failsafe, now)
        self.queue.clear()
        # The watches' turns queued are gone with the queue: the restarted service's
        # watches queue their own (as a new process's tasks do).
        self._check_queued = self._failsafe_queued = False
        self.parked.clear()
        self.busy = None
        self.streams.clear()
        for controller in self.world.live_controllers():
            controller.drone_link.break_("drone restart")

    def restart(self) -> None:
        """The drone service starts again from its durable state (DroneService._restore)."""
        self.up = True
        self.vehicle.gcs_heard()
        self.stats.restarts += 1
        self.core, effects = self._restored()
        # PolicyRunner is built afresh, with the hold the store keeps (PolicyRunner.restore).
        held = self.policy is not None and self.policy.held_vehicle
        self.policy = self._policy_runner()
        if self.policy is not None:
            self.policy.restore(held, self.intent)
        self.watch()
        self.world.trace(f"drone restarts (cut off: {self.intent})")
        if self.intent is not None:
            self.stats.cut_off.append(self.intent)
        self._apply(effects)

    def _gcs_failsafe(self, silent_since: float) -> None:
        """The autopilot's GCS failsafe timer ran out: if the drone service is silent since
        ``silent_since`` still, the vehicle returns, and lands after a drawn while."""
        now = self.world.loop.now
        if self.vehicle.gcs_failsafe(now, silent_since, self.world.mission_open()):
            self.world.trace("the autopilot's GCS failsafe: the vehicle returns")
            landing = self.world.gcs_rng.uniform(0.05, 1.0)
            self.world.loop.after(landing, self._landed_by_itself)

    def _landed_by_itself(self) -> None:
        self.vehicle.land(self.world.loop.now)
        self.world.trace("the vehicle landed by itself (its GCS failsafe)")

    def _sequencer(self) -> Sequencer:
        """A new Sequencer as DroneService's factory makes it (nothing served yet)."""
        seq = Sequencer(
            self.controllers,
            self.initial_master,
            self.script,
            self.cache_window,
            self.prepare_timeout_s,
        )
        if self.signer is not None:
            seq.sign_grants_with(self.signer.seal_grant)
        return seq

    def _restored(self) -> tuple[DroneCore, list[DroneEffect]]:
        """A new core holding what the store keeps (``DroneCore.restarted``, as
        DroneService._restore), and the effects of the restart: the sightings are not
        kept (the master gets the restart grace)."""
        old, now = self.seq, self.world.loop.now
        core = DroneCore(self._sequencer(), self.world.takeover_after, self.world.safety)
        # The operator's state as the store keeps it (OperatorCommands._save, .restore).
        core.operator = Operator.from_json(self.core.operator.to_json())
        replies = [old.cache.get(reqnr) for reqnr in old.cache.reqnrs]
        stored = DroneState(
            counters_of(old), [r for r in replies if r is not None], list(old.audit), self.intent
        )
        # The vehicle command and the failsafe are kept in the store whenever they change.
        kept = Kept.of(stored, self.core.kept_command(), self.core.failsafe)
        return core, core.restarted(now, kept)

    # -- takeover (DroneService.watch_master, _take_over) ------------------------

    def reachable(self) -> set[int]:
        """StandbyStreams.reachable | MasterStreams.holders: controllers holding a stream.

        Simplification: a live controller's standby stream is up exactly while
        its channel is usable (a kill or a partition ends it at once, as a
        reset TCP connection does; it is back as soon as the channel is).
        """
        if not self.up:
            return set()
        world = self.world
        return {cid for cid in self.controllers if world.controller(cid).drone_link.usable()}

    def watch(self) -> None:
        """Starts ``watch_master``'s loop if it is not running (at start and restarts, and
        for a prepared handover's deadline), and the policy's and the radio's."""
        if self.policy is not None and self.up:
            self.policy.start()
        if self.world.corridor is not None:
            self.world.corridor.tick()
        takeovers = self.core.takeover_after_s > 0 or self.core.safety.lost_link_s > 0
        if not self._watching and self.up and (takeovers or self.seq.preparing):
            self._watching = True
            self.world.loop.after(WATCH_TICK_S, self._watch_master)

    def _watch_master(self) -> None:
        """One turn of DroneService.watch_master: note who is reachable, ask takeover_due.

        The loop stops (to let a finished run end) once no program has
        calls left nor a given-up call to settle (``World.mission_open``);
        ``World`` starts it again when a program (re)starts.
        """
        self._watching = False
        # DroneService.watch_master never stops: it forces a preparation left at the
        # end of the mission at its deadline too.
        if not self.up or not (self.world.mission_open() or self.seq.preparing):
            return
        now = self.world.loop.now
        preparing = self.seq.preparing
        expired = preparing is not None and now >= preparing.deadline
        due = self.sight().takeover_due(self.core, now)
        if (due is not None or expired) and not self._check_queued:
            # async with self._lock: asked again there. The service takes the lock at
            # every turn while preparing; only a turn at or past the deadline can force.
            self._check_queued = True
            self.queue.append(MasterCheck())
            self._next()
        if self._failsafe_due(now) is not None and not self._failsafe_queued:
            self._failsafe_queued = True  # FailsafeWatch.run: async with the lock
            self.queue.append(FailsafeCheck())
            self._next()
        self.watch()

    def sight(self) -> DroneSight:
        """The controllers as the watches see them (``DroneService.sight``)."""
        in_range = self.policy.in_range() if self.policy is not None else None
        return DroneSight(self.reachable(), self.seq.master in self.streams, in_range)

    def _failsafe_due(self, now: float) -> Failsafe | None:
        """The failsafe due for the vehicle as it is: armed and in the air while the
        mission is open, unless its GCS failsafe landed it, in the mode its commands and
        the autopilot's takeover put it in; no position (no fence, no nearest station)."""
        vehicle = self.vehicle
        airborne = vehicle.in_air(self.world.mission_open())
        seen = ModeSeen(vehicle.mode, not vehicle.landed, airborne)
        battery = vehicle.battery(now)
        return self.sight().failsafe_check(self.core, now, airborne, battery, None, seen)

    def _failsafe_check(self) -> None:
        """FailsafeWatch.run under the lock: failsafe_due again, then entered and commanded."""
        now = self.world.loop.now
        due = self._failsafe_due(now)
        if due is not None:
            self.core.enter_failsafe(due)
            if due.drone_acts:
                self.vehicle.obey(commanded_action(due.action))
            self.vehicle.failsafes.append((now, f"{due.cause} {due.action}"))
            self.world.trace(f"failsafe: {due.reason}")

    def operator_rpc(self, command: str, action: str = "") -> None:
        """Drone.Pause, Resume, Abort or LandNow: takes the lock, then decides."""
        if not self.up:
            return  # the operator's call fails UNAVAILABLE
        self.queue.append(OperatorOrder(command, action))
        self._next()

    def _operator(self, order: OperatorOrder) -> None:
        """OperatorCommands._command under the lock: the core decides (a refusal is the
        operator's error, nothing changes); the vehicle is told; a pause's end lets the
        requests that waited go on, to be executed or refused."""
        now = self.world.loop.now
        try:
            taken, cleared = self.core.operator_command(order.command, now, order.action)
        except StatusError as err:
            self.world.trace(f"operator command refused: {err.message}")
            return
        if order.command == "resume":
            self.vehicle.resumes.append(now)
        if cleared is not None:
            self.world.trace(f"failsafe cleared by the operator ({cleared.cause})")
        self.vehicle.operator.append((now, taken.command, taken.action))
        self.world.trace(f"operator: {taken.reason}")
        if taken.command != "pause":
            self.queue.extend(self.parked)  # their waits end: each takes the lock again
            self.parked.clear()

    def standby_opened(self, cid: int) -> None:
        """DroneService.Standby: a controller's standby stream (re)opens; a TakeOver still
        owed to it is told on it (the stream that was to carry it may have broken)."""
        owed = self.core.takeover_owed(cid) if self.up else None
        if owed is not None:
            self._tell_take_over(cid, owed)

    def _tell_take_over(self, taker: int, told: drone_pb2.TakeOver) -> None:
        """StandbyStreams.tell of the TakeOver, on the taker's newest stream if it holds
        one (the retained replies follow its Connected)."""
        link = self.world.controller(taker).drone_link
        if not link.usable():
            return
        link.to_controller(link.generation, 0, link.owner.on_take_over, told, stream=True)


def _ending(record: drone_pb2.HandoverRecord, on_the_word: bool) -> str:
    """How a handover ended, for the counts: prepared (on the master's word between
    requests, or at a request), forced at the prepare timeout, at once, or a takeover."""
    if record.kind == drone_pb2.HANDOVER_KIND_PREPARED:
        return "prepared on the word" if on_the_word else "prepared at a request"
    if record.prepare_timed_out:
        return "forced at the timeout"
    if record.kind == drone_pb2.HANDOVER_KIND_TAKEOVER:
        return "takeover"
    return "cooperative at once"


def _acted_on(request: Request) -> None:
    """For the oracles: the drone served ``request`` (or answered it again), so what its
    sender's program had consumed when it sent it left the sender."""
    if request.sender is not None:
        sender = request.sender
        sender.accepted_upto = max(sender.accepted_upto, request.consumed)
