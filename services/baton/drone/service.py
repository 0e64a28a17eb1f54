"""The Drone gRPC service: Invoke for the master, Connect, Handover, GetStatus.

The drone executes one request at a time, in reqnr order, for the master
only (Section 4 of the paper). ``_lock`` is that single line of execution: a
request is checked and executed under it, and a handover takes it too, so a
switch always falls between two requests and every request is answered by
the master that was master when it was executed.
"""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import AsyncIterator, Iterable, Mapping
from typing import Any

import grpc

from baton.authenticity import Signer, signed_reply, signed_retained
from baton.digest import request_digest
from baton.drone.camera import Camera
from baton.drone.connects import ConnectStream
from baton.drone.core import WATCH_TICK_S, DroneCore, Kept
from baton.drone.dedupe import CachedReply
from baton.drone.dispatch import Dispatcher
from baton.drone.effects import (
    Abandon,
    Book,
    DroneEffect,
    Preparing,
    SaveCounters,
    Switched,
    TellTakeOver,
    pins_policy,
    take_over_event,
)
from baton.drone.failsafe_watch import FailsafeWatch
from baton.drone.invariants import INVARIANT_EXIT, DroneWatch, InvariantBroken, checking
from baton.drone.link_probe import PING_PERIOD_S, LinkProbes
from baton.drone.master import MasterStreams, StandbyStreams
from baton.drone.mobility_api import MobilityBackend
from baton.drone.operator_service import OperatorCommands
from baton.drone.policy import LinkBounds, LinkState, Station
from baton.drone.policy_runner import PolicyRunner
from baton.drone.safety import (
    VEHICLE_ACTIONS,
    SafetyParams,
)
from baton.drone.sequencer import Sequencer, TakeoverDue
from baton.drone.settings import Race
from baton.drone.status import StallWatcher, drone_status
from baton.drone.store import Counters, DroneStore, Intent
from baton.logs import get_logger
from baton.rpc.errors import StatusError, abort_with
from baton.rpc.labels import label
from baton.rpc.outcomes import failure_of
from baton.rpc.tls import OPERATOR, Identity, refused, refused_status
from baton.stalls import Wait, one_line
from baton.tasks import TaskSet
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2, drone_pb2_grpc

# The durable commanded state's key of the mission's cruise speed (store.py).
SPEED_KEY = "speed_m_s"
# ... and of what the drone last commanded the vehicle (DroneCore.vehicle_command).
VEHICLE_COMMAND_KEY = "vehicle_command"


def _retrieve_exception(task: asyncio.Task[Any]) -> None:
    """Marks a shielded request's failure as seen when its caller is gone (no asyncio warning)."""
    if not task.cancelled():
        task.exception()


class DroneService(drone_pb2_grpc.DroneServicer):
    """The drone middleware of drone.proto, over a vehicle backend and a camera.

    Every decision (who may invoke, in which epoch, which request numbers,
    duplicates, the script, who is lost and who takes over) is the pure
    ``DroneCore``'s; this class executes what it admits, keeps the streams,
    and saves the outcome.
    """

    def __init__(
        self,
        vehicle: MobilityBackend,
        camera: Camera,
        sequencer: Sequencer,
        race: Race | None = None,
        store: DroneStore | None = None,
        takeover_after_s: float = 0.0,
        authenticated: bool = False,
        link_bounds: LinkBounds | None = None,
        safety: SafetyParams | None = None,
        stations: Mapping[int, Station] | None = None,
    ) -> None:
        self.race = race
        # Signs every reply the drone makes (baton.authenticity); None: insecure, unsigned.
        self.signer: Signer | None = None
        # Mutual TLS on the port: every call is checked against the caller's
        # certificate (docs/design.md, Security); False: anyone may call.
        self.authenticated = authenticated
        self.store = store
        self.vehicle = vehicle
        self.camera = camera
        # The master is lost after takeover_after_s (wall seconds) without a
        # stream or a request; 0: never (only an operator's takeover).
        watch = DroneWatch() if checking() else None  # BATON_CHECK_INVARIANTS=1
        self.core = DroneCore(sequencer, takeover_after_s, safety, watch)
        # The vehicle command as the state file keeps it (``keep_command``).
        self._kept_command: dict[str, Any] | None = None
        # Every controller's station: the landing points of nearest_station.
        self.stations: Mapping[int, Station] = stations or {}
        self.seq = sequencer
        self.streams = MasterStreams(sequencer)
        self.standby = StandbyStreams()
        self._handed_over_after = 0
        # Set (and replaced) at every switch: a prepared Handover call waits on it.
        self._switch_seen = asyncio.Event()
        self.dispatcher = Dispatcher({"Mobility": vehicle, "Camera": camera})
        self._lock = asyncio.Lock()
        # The invocations running to their end, held while their callers may be gone.
        self._invocations = TaskSet()
        self.log = get_logger("drone").bind(
            context=lambda: {
                "master": self.seq.master,
                "epoch": self.seq.epoch,
                "last_reqnr": self.seq.last_reqnr,
            }
        )
        # The waits into GetStatus, and the stalls into the log (status.StallWatcher).
        self.stalls = StallWatcher(self)
        # Each controller's round trip, measured by pings on its standby stream.
        self.probes = LinkProbes(tuple(sequencer.ring), link_bounds or LinkBounds(), self.log)
        # The handover policy, when the drone runs one (build_service).
        self.policy: PolicyRunner | None = None
        # The request a restart cut off (store.py's intent), as found at start.
        self.cut_off: Intent | None = None
        # Pause, Resume, Abort, LandNow (operator_service.py).
        self.operator = OperatorCommands(self)
        # The safety net's look at the vehicle (failsafe_watch.py).
        self.failsafes = FailsafeWatch(self)
        if store is not None:
            self._restore(store)

    @property
    def takeover_after_s(self) -> float:
        """The takeover time in wall seconds (0: never)."""
        return self.core.takeover_after_s

    @takeover_after_s.setter
    def takeover_after_s(self, seconds: float) -> None:
        self.core.takeover_after_s = seconds

    @property
    def execution_lock(self) -> asyncio.Lock:
        """The single line of execution: held to execute a request or move the master."""
        return self._lock

    @property
    def last_reqnr(self) -> int:
        """The last request number served."""
        return self.seq.last_reqnr

    @property
    def audit(self) -> list[drone_pb2.AuditEntry]:
        """The newest served requests held in memory, in order."""
        return list(self.seq.audit)

    @property
    def waits(self) -> list[Wait]:
        """What the drone waits for now (``status.StallWatcher``)."""
        return self.stalls.waits

    @property
    def waiting(self) -> str:
        """The waits that need a person, as one line; empty when none does."""
        return one_line(self.waits)

    async def watch_master(self) -> None:
        """Every tick: the master taken over when it is lost, a preparation forced at its
        deadline (``DroneCore.master_watch``)."""
        while True:
            if self._takeover_due() is not None or self.seq.preparing is not None:
                async with self._lock:
                    # Asked again under the lock: a request may have come meanwhile.
                    in_range = self.policy.in_range() if self.policy is not None else None
                    where = self.policy.position if self.policy is not None else None
                    self.apply(
                        self.core.master_watch(
                            time.time(), *self._stream_holders(), in_range, where
                        )
                    )
            await asyncio.sleep(WATCH_TICK_S)

    def commanded(self, action: str | None) -> None:
        """The vehicle accepted a command for ``action`` (``DroneCore.commanded``; the
        caller told the core ``commanding`` before sending it), kept in the state file."""
        self.core.commanded(action, time.time())
        self.keep_command()

    def keep_command(self) -> None:
        """Keeps the vehicle command in the state file when it changed
        (``DroneCore.kept_command``): its actions, and the vehicle seen in the air."""
        kept = self.core.kept_command()
        if kept != self._kept_command and self.store is not None:
            self.store.save_commanded(VEHICLE_COMMAND_KEY, kept)
            self._kept_command = kept

    def save_failsafe(self) -> None:
        if self.store is not None:
            self.store.save_failsafe(self.core.failsafe)

    # -- an operator's commands (operator_service.py) --------------------------------

    async def Resume(
        self, request: drone_pb2.ResumeRequest, context: grpc.aio.ServicerContext
    ) -> drone_pb2.ResumeReply:
        return await self.operator.resume(request, context)

    async def Pause(
        self, request: drone_pb2.PauseRequest, context: grpc.aio.ServicerContext
    ) -> drone_pb2.OperatorReply:
        return await self.operator.pause(request, context)

    async def Abort(
        self, request: drone_pb2.AbortRequest, context: grpc.aio.ServicerContext
    ) -> drone_pb2.OperatorReply:
        return await self.operator.abort(request, context)

    async def LandNow(
        self, request: drone_pb2.LandNowRequest, context: grpc.aio.ServicerContext
    ) -> drone_pb2.OperatorReply:
        return await self.operator.land_now(request, context)

    async def watch_links(self) -> None:
        """Every PING_PERIOD_S: pings each controller on its standby stream, and logs
        the links that went unhealthy or healthy (``LinkProbes``)."""
        while True:
            now = time.monotonic()
            for cid in self.standby.reachable:
                self.standby.tell(cid, self.probes.ping(cid, now))
            self.probes.watch(self.link_states())
            await asyncio.sleep(PING_PERIOD_S)

    def link_states(self, speedup: float = 1.0) -> dict[int, LinkState]:
        """Each controller's link: up while it holds a standby or Connect stream, else
        down since last seen (times ``speedup``: mission seconds), and its round trip.

        One not seen since the drone started counts as seen at the end of the
        start-up grace (``unseen_from``), as the takeover watch counts it: the
        controllers come up one by one, and the first to come must not take the
        master over from one still starting."""
        up = self.standby.reachable | self.streams.holders
        now, clock = time.time(), time.monotonic()
        links = {}
        for cid in self.seq.ring:
            down = 0.0
            if cid not in up:
                down = (self.core.down_for(cid, now) or 0.0) * speedup
            links[cid] = self.probes.state(cid, cid in up, down, clock)
        return links

    def _stream_holders(self) -> tuple[set[int], set[int]]:
        """Who holds a stream now, and who holds the master's Connect stream."""
        holders = self.standby.reachable | self.streams.holders
        return holders, ({self.seq.master} if self.streams.master_connected else set())

    def _takeover_due(self) -> TakeoverDue | None:
        """``DroneCore.takeover_due`` with who holds a stream now and who is in range."""
        in_range = self.policy.in_range() if self.policy is not None else None
        return self.core.takeover_due(time.time(), *self._stream_holders(), in_range)

    def apply(self, effects: Iterable[DroneEffect], notice_delay_s: float = 0.0) -> None:
        """Carries out the core's effects in their order (``effects.py``), under the lock.
        ``notice_delay_s`` holds a switch's notice back (``Race``)."""
        for effect in effects:
            if isinstance(effect, Abandon):
                if self.store is not None:
                    self.store.abandon()
            elif isinstance(effect, Book):
                if self.store is not None:
                    served = effect.served
                    counters, oldest = self._counters(), self.seq.cache.reqnrs[0]
                    self.store.served(counters, served.cached, served.audit, oldest)
            elif isinstance(effect, SaveCounters):
                if self.store is not None:
                    self.store.save(self._counters())
            elif isinstance(effect, Switched):
                self._switched(effect.record, notice_delay_s)
            elif isinstance(effect, Preparing):
                self.log.info(
                    "preparing a handover",
                    target=effect.notice.target,
                    timeout_s=effect.notice.timeout_s,
                    master_connected=self.streams.master_connected,
                )
                self.streams.wake(self.seq.master)
            elif isinstance(effect, TellTakeOver):
                self._tell_take_over(effect)
            else:
                (self.log.warning if effect.level == "warning" else self.log.info)(
                    effect.event, **effect.fields
                )

    def _tell_take_over(self, effect: TellTakeOver) -> None:
        record, lost_at = effect.record, effect.lost_at
        told = self.standby.tell(
            record.new_master, drone_pb2.StandbyEvent(take_over=effect.take_over)
        )
        retained, retained_bytes = self.seq.cache.retained
        lost = record.trigger == drone_pb2.HANDOVER_TRIGGER_LOST
        self.log.warning(
            "master lost: taken over" if lost else "takeover",
            lost=record.old_master,
            new_master=record.new_master,
            epoch=record.epoch,
            unseen_s=round(record.decided_at - lost_at, 3) if lost_at else None,
            watermark_reqnr=self.seq.cache.watermark,
            retained_replies=retained,
            retained_bytes=retained_bytes,
            told_on_standby=told,
        )

    # -- durable state (store.py) ---------------------------------------------------

    def _counters(self) -> Counters:
        seq = self.seq
        return Counters(
            master=seq.master,
            last_reqnr=seq.last_reqnr,
            executed=seq.executed,
            duplicates=seq.duplicates,
            rejected=seq.rejected,
            handovers=list(seq.handovers),
            fired_script=list(seq.fired_script),
            watermark=seq.cache.watermark,
        )

    def _restore(self, store: DroneStore) -> None:
        """Resumes from the store (``DroneCore.restarted``): master, counters, replies,
        audit, script, the vehicle's commanded state, a failsafe, a request cut off."""
        state = store.load()
        if state is None:
            store.save(self._counters())
            self.log.info("new state file", path=str(store.path))
            return
        c, seq, commanded = state.counters, self.seq, store.load_commanded()
        speed = commanded.get(SPEED_KEY)
        if speed is not None:
            self.vehicle.restore_speed(float(speed))
            self.log.info("cruise speed restored", speed_m_s=speed)
        modes = commanded.get(VEHICLE_COMMAND_KEY)
        failsafe = store.load_failsafe()
        if failsafe is not None:
            self.log.warning("still in failsafe", cause=failsafe.cause, reason=failsafe.reason)
        self.operator.restore()
        cut = self.cut_off = state.executing
        kept = Kept(
            c.master,
            c.handovers,
            (c.last_reqnr, c.executed, c.duplicates, c.rejected),
            state.replies,
            state.audit,
            c.fired_script,
            c.watermark,
            modes,
            failsafe,
            cut,
        )
        effects = self.core.restarted(time.time(), kept)
        self._kept_command = self.core.kept_command()
        self.log.info(
            "state resumed",
            path=str(store.path),
            master=c.master,
            epoch=seq.epoch,
            last_reqnr=c.last_reqnr,
            cached_replies=len(state.replies),
            audit=len(state.audit),
            script_left=len(seq.script),
        )
        self._served(0 if cut is None else cut.reqnr, effects)

    async def Invoke(
        self, request: drone_pb2.InvokeRequest, context: grpc.aio.ServicerContext
    ) -> drone_pb2.InvokeReply:
        """Executes one drone-API call for the master, or answers it from the reply cache."""
        try:
            return await self._invoke_for(context, request, time.time())
        except StatusError as err:
            await abort_with(context, err)

    async def InvokeStream(  # type: ignore[override]  # writes with context.write
        self,
        calls: AsyncIterator[drone_pb2.InvokeCall],
        context: grpc.aio.ServicerContext,
    ) -> None:
        """Invoke's calls as messages on one stream: each is executed as Invoke
        executes it and answered when it completes, its failure in its outcome.

        Calls run concurrently as their Invokes would (the sequencer's lock
        orders them); their outcomes are written one at a time. When the
        caller half-closes, the stream ends once every call has its outcome;
        when it goes away, what is still running runs to its end
        (``invoke``) and its outcome is dropped, as a cancelled Invoke's is.
        """
        answering = TaskSet()
        writing = asyncio.Lock()

        async def answer(call: drone_pb2.InvokeCall, received_at: float) -> None:
            outcome = drone_pb2.InvokeOutcome(call=call.call)
            try:
                outcome.reply.CopyFrom(await self._invoke_for(context, call.request, received_at))
            except StatusError as err:
                outcome.failure.CopyFrom(failure_of(err))
            except Exception as exc:  # what a unary Invoke would end with: UNKNOWN
                self.log.error("invoke failed", exc_info=True, reqnr=call.request.reqnr)
                unknown = StatusError(grpc.StatusCode.UNKNOWN, f"{type(exc).__name__}: {exc}")
                outcome.failure.CopyFrom(failure_of(unknown))
            try:
                async with writing:
                    await context.write(outcome)
            except Exception as exc:  # the stream ended: the caller sends it again
                self.log.info(
                    "invoke outcome not delivered: its stream ended",
                    reqnr=call.request.reqnr,
                    error=f"{type(exc).__name__}: {exc}",
                )

        try:
            async for call in calls:
                answering.spawn(answer(call, time.time()), name="invoke-call")
            await answering.drain()
        finally:
            answering.cancel()

    async def _invoke_for(
        self,
        context: grpc.aio.ServicerContext,
        request: drone_pb2.InvokeRequest,
        received_at: float,
    ) -> drone_pb2.InvokeReply:
        """Invoke for the caller of ``context``: the reply, or StatusError (counted and
        logged) if the caller may not send it or the drone refused or failed it."""
        try:
            refusal = self._not_as(context, "Invoke", request.controller_id)
            if refusal is not None:
                raise refusal
            return await self.invoke(request, received_at)
        except StatusError as err:
            self.seq.rejected += 1
            self.log.warning(
                "invoke rejected",
                controller=request.controller_id,
                reqnr=request.reqnr,
                request_epoch=request.epoch,
                method=request.method,
                code=err.code.name,
                reason=err.message,
            )
            raise

    async def invoke(
        self, request: drone_pb2.InvokeRequest, received_at: float
    ) -> drone_pb2.InvokeReply:
        """Invoke without gRPC: the reply, or StatusError saying why not.

        Three kinds of failure: the sequencer's refusals (not the master, a
        stale epoch, a wrong reqnr, a duplicate that differs) leave the reqnr
        unused and carry ``baton-master`` / ``baton-epoch`` /
        ``baton-after-reqnr`` metadata; UNAVAILABLE (the vehicle not
        connected, no telemetry yet) means nothing was executed, so the reqnr
        stays unused too and the same request can be sent again; any other
        failure after the reqnr was accepted (bad method or payload,
        autopilot refusal, no acknowledgement in time) is served with that
        failure, which is cached and given again to a duplicate (dedupe.py).

        A request runs to its end once it is received, whatever its caller
        does: it is a task of its own that the caller's cancellation (a
        deadline, a client that gave up) does not reach, so what the vehicle
        did is always recorded and a re-sent reqnr is answered from the
        cache, never executed again. A duplicate that arrives meanwhile
        waits for it (the lock) and gets its outcome.
        """
        while True:
            await self.operator.wait_resumed(request)  # paused: waits, not admitted
            task = self._invocations.spawn(self._invoke_to_the_end(request, received_at))
            task.add_done_callback(_retrieve_exception)
            reply = await asyncio.shield(task)
            if reply is not None:
                return reply

    async def _invoke_to_the_end(
        self, request: drone_pb2.InvokeRequest, received_at: float
    ) -> drone_pb2.InvokeReply | None:
        """The request under the execution lock, to its end; None when a pause came before
        it got the lock (it waits again, not admitted)."""
        cid, reqnr, method = request.controller_id, request.reqnr, request.method
        async with self._lock:
            if self.core.holds(request):
                return None
            digest = request_digest(method, request.payload)
            try:
                admitted = self.core.admit(request, digest, received_at)
            except InvariantBroken as broken:
                # A defect of baton: stop as a kill -9 would, rather than fly on.
                self.log.error("invariant broken; the drone service stops", problem=str(broken))
                os._exit(INVARIANT_EXIT)
            first = admitted.first
            if first is not None:
                self.log.info(
                    "first request of new master",
                    master=cid,
                    epoch=first.epoch,
                    after_reqnr=first.after_reqnr,
                    delay_s=round(first.delay_s, 6),
                )
            if admitted.cached is not None:
                return self._answer_duplicate(request, admitted.cached)
            if self.store is not None:
                self.store.begin(Intent(reqnr, method, digest, cid, received_at), admitted.kept)
            try:
                if admitted.refused is not None:
                    raise admitted.refused
                reply = await self._execute(request)
            except StatusError as err:
                now = time.time()
                self._served(
                    reqnr, self.core.failed(cid, reqnr, method, digest, received_at, now, err)
                )
                raise
            self._served(
                reqnr, self.core.served(cid, reqnr, method, digest, reply, received_at, time.time())
            )
            epoch = self.seq.epoch
        if (
            self.race is not None
            and self.race.order == "notice-first"
            and self._handed_over_after == reqnr
        ):
            await asyncio.sleep(self.race.delay_s)
        return signed_reply(self.signer, reqnr, epoch, method, digest, reply)

    def _answer_duplicate(
        self, request: drone_pb2.InvokeRequest, cached: CachedReply
    ) -> drone_pb2.InvokeReply:
        self.log.info(
            "duplicate answered from cache",
            controller=request.controller_id,
            reqnr=request.reqnr,
            method=request.method,
            failed=cached.error is not None,
        )
        error = cached.duplicate_error()
        if error is not None:
            raise error
        return signed_reply(
            self.signer,
            request.reqnr,
            cached.epoch,
            cached.method,
            cached.digest,
            cached.reply,
            duplicate=True,
        )

    async def _execute(self, request: drone_pb2.InvokeRequest) -> bytes:
        route = self.dispatcher.route(request.method)
        message = route.parse(request.payload)
        why = f"at {self.vehicle.url} ({self.vehicle.link().problem})"
        unreachable = self.core.unreachable(request.method, self.vehicle.connected, why)
        if unreachable is not None:
            raise unreachable
        handler = self.dispatcher.handler(route)
        action = VEHICLE_ACTIONS.get(route.name) if route.service == "Mobility" else None
        self.core.commanding(action, time.time())
        try:
            reply = await handler(message)
        except StatusError:
            raise
        except Exception as exc:
            self.log.error("handler failed", method=request.method, exc_info=True)
            raise StatusError(
                grpc.StatusCode.INTERNAL, f"{request.method} failed on the drone: {exc!r}"
            ) from exc
        if route.service == "Mobility":
            self.commanded(action)
            self.operator.executed(route.name, request.payload)
            if self.policy is not None:
                self.policy.executed(route.name, message)
        if self.store is not None and isinstance(message, api.SetSpeedRequest):
            # Commanded state the vehicle needs again after a restart (store.py).
            self.store.save_commanded(SPEED_KEY, message.speed_m_s)
        payload = reply.SerializeToString()
        log = self.log.debug if route.is_read else self.log.info
        log(
            "executed",
            controller=request.controller_id,
            reqnr=request.reqnr,
            method=request.method,
            reply_bytes=len(payload),
        )
        return payload

    def _served(self, reqnr: int, effects: list[DroneEffect]) -> None:
        """Applies a served request's effects (``DroneCore.served``): booked and saved, and
        the script's handover or preparation after it."""
        race = self.race
        hold = race.delay_s if race is not None and race.order == "reply-first" else 0.0
        self.apply(effects, notice_delay_s=hold)
        if any(isinstance(effect, Switched) for effect in effects):
            self._handed_over_after = reqnr

    def _switched(self, record: drone_pb2.HandoverRecord, notice_delay_s: float = 0.0) -> None:
        """Logs a switch, pins the policy to a master the script or an operator chose, and
        wakes the old master's stream to carry the notice and a prepared Handover call."""
        prepared = {}
        if record.prepare_started_at:
            prepared = {
                "prepared_s": round(record.decided_at - record.prepare_started_at, 6),
                "prepare_timed_out": record.prepare_timed_out,
                "lacked_bytes": record.prepare_lacked_bytes,
            }
        log = self.log.warning if record.prepare_timed_out else self.log.info
        log(
            "handover",
            old_master=record.old_master,
            new_master=record.new_master,
            after_reqnr=record.after_reqnr,
            epoch=record.epoch,
            trigger=label(drone_pb2.HandoverTrigger, record.trigger),
            kind=label(drone_pb2.HandoverKind, record.kind),
            old_master_connected=self.streams.connected(record.old_master),
            **prepared,
            reason=record.reason or None,
        )
        if self.policy is not None and pins_policy(record):
            self.policy.pin(record.new_master)
        self.streams.wake(record.old_master, notice_delay_s)
        self._switch_seen.set()
        self._switch_seen = asyncio.Event()

    def _not_as(self, context: grpc.aio.ServicerContext, what: str, cid: int) -> StatusError | None:
        """Why the caller may not make ``what`` as controller ``cid``, or None: the
        identity comes from its certificate, the request's controller_id must match."""
        claimed = Identity.controller(cid)
        return refused(
            context,
            self.authenticated,
            f"{what} as controller {cid}",
            f"only the certificate of {claimed.uri} may send controller_id {cid}",
            lambda who: who == claimed,
        )

    async def Connect(
        self, request: drone_pb2.ConnectRequest, context: grpc.aio.ServicerContext
    ) -> AsyncIterator[drone_pb2.DroneEvent]:
        """The master's event stream: what ``connects.ConnectStream`` says, in order."""
        cid = request.controller_id
        try:
            refusal = self._not_as(context, "Connect", cid)
            if refusal is not None:
                raise refusal
            if self.seq.fresh_self_due(cid, request.mastership_epoch, request.given_up_epoch):
                async with self._lock:
                    self.apply(
                        self.core.fresh_self_connect(cid, request.given_up_epoch, time.time())
                    )
            stream = self.streams.attach(cid, request.mastership_epoch)
        except StatusError as err:
            self.log.warning("connect rejected", controller=cid, reason=err.message)
            await abort_with(context, err)
        self.log.info("master connected", controller=cid)
        said = ConnectStream(cid)
        try:
            grant, batches = said.opened(self.core, request.holds_reqnr)
            if grant is not None:
                yield drone_pb2.DroneEvent(connected=grant)
            for batch in batches:
                replies = [signed_retained(self.signer, r.to_proto()) for r in batch]
                yield drone_pb2.DroneEvent(retained=drone_pb2.RetainedBatch(replies=replies))
            while True:
                for event in said.woken(self.core):
                    if isinstance(event, drone_pb2.OperatorWord):
                        yield drone_pb2.DroneEvent(operator=event)
                    elif isinstance(event, drone_pb2.PrepareHandover):
                        yield drone_pb2.DroneEvent(prepare=event)
                    else:
                        yield drone_pb2.DroneEvent(handover=event)
                        self.core.delivered(cid, event)
                        self.log.info(
                            "handover notice delivered",
                            controller=cid,
                            new_master=event.new_master,
                            after_reqnr=event.after_reqnr,
                            epoch=event.epoch,
                        )
                        return
                if stream.superseded:
                    return
                await stream.wake.wait()
                stream.wake.clear()
        finally:
            self.streams.detach(stream)
            self.log.info("connect stream ended", controller=cid)

    async def Standby(
        self, request: drone_pb2.StandbyRequest, context: grpc.aio.ServicerContext
    ) -> AsyncIterator[drone_pb2.StandbyEvent]:
        """A controller's standby stream: held while it runs; a TakeOver comes here."""
        cid = request.controller_id
        try:
            refusal = self._not_as(context, "Standby", cid)
            if refusal is not None:
                raise refusal
            self.seq.check_known(cid)
        except StatusError as err:
            self.log.warning("standby rejected", controller=cid, reason=err.message)
            await abort_with(context, err)
        stream = self.standby.attach(cid)
        self.probes.attached(cid)
        self.core.seen(cid, time.time())
        try:
            yield drone_pb2.StandbyEvent(
                held=drone_pb2.StandbyHeld(master=self.seq.master, epoch=self.seq.epoch)
            )
            owed = self.core.takeover_owed(cid)
            if owed is not None:  # the stream that was to carry it may have broken first
                told = take_over_event(owed, self.seq.cache.watermark)
                yield drone_pb2.StandbyEvent(take_over=told)
            while True:
                yield await stream.events.get()
        finally:
            self.standby.detach(stream)
            self.core.seen(cid, time.time())

    async def AnswerPing(
        self, request: drone_pb2.PingAnswer, context: grpc.aio.ServicerContext
    ) -> drone_pb2.PingAnswerReply:
        """A controller's answer to a LinkPing: its link's round trip measured."""
        arrived = time.monotonic()
        refusal = self._not_as(context, "AnswerPing", request.controller_id)
        if refusal is not None:
            await abort_with(context, refusal)
        measured = self.probes.answered(request.controller_id, request.seq, arrived)
        return drone_pb2.PingAnswerReply(measured=measured)

    async def Handover(
        self, request: drone_pb2.HandoverRequest, context: grpc.aio.ServicerContext
    ) -> drone_pb2.HandoverReply:
        """Switches the master after the request being served, if any
        (``DroneCore.handover_call``); a prepared one is answered once the master moved.

        INVALID_ARGUMENT for an unknown id; FAILED_PRECONDITION if the id
        already is the master (not a silent no-op: a caller asking for a
        switch should learn that none happened), unless it is a takeover
        that re-grants a new master still waiting for a lost one's log.
        """
        try:
            refusal = refused(
                context,
                self.authenticated,
                "Handover",
                f"only an operator ({OPERATOR.uri}) may move the master; a controller is "
                "made master by the drone",
                lambda who: who == OPERATOR,
            )
            if refusal is not None:
                raise refusal
            new_master = request.new_master
            async with self._lock:
                effects = self.core.handover_call(
                    new_master,
                    request.prepared,
                    request.takeover,
                    self.streams.master_connected,
                    time.time(),
                )
                self.apply(effects)
                preparation = self.seq.preparing
            if any(isinstance(effect, Preparing) for effect in effects):
                assert preparation is not None
                while self.seq.preparing is preparation:
                    await self._switch_seen.wait()
                record = self.core.prepared_outcome(new_master, preparation.started_at)
            else:
                record = self.seq.handovers[-1]
        except StatusError as err:
            self.log.warning("handover rejected", new_master=request.new_master, reason=err.message)
            await abort_with(context, err)
        return drone_pb2.HandoverReply(
            old_master=record.old_master,
            new_master=record.new_master,
            after_reqnr=record.after_reqnr,
            epoch=record.epoch,
        )

    async def ReportPreparation(
        self, request: drone_pb2.PreparationReport, context: grpc.aio.ServicerContext
    ) -> drone_pb2.PreparationReportReply:
        """The master's word between requests: the master moves now if its target
        caught up (after the request being served, if any: the lock)."""
        cid = request.controller_id
        refusal = self._not_as(context, "ReportPreparation", cid)
        if refusal is not None:
            await abort_with(context, refusal)
        async with self._lock:
            effects = self.core.preparation_word(cid, request.epoch, request.progress, time.time())
            self.apply(effects)
        return drone_pb2.PreparationReportReply(moved=bool(effects))

    async def GetStatus(
        self, request: drone_pb2.GetDroneStatusRequest, context: grpc.aio.ServicerContext
    ) -> drone_pb2.DroneStatus:
        """The drone's state, counters, handovers and (if asked) the command audit."""
        refusal = refused_status(context, self.authenticated)
        if refusal is not None:
            await abort_with(context, refusal)
        return await self.status(
            request.include_audit, request.audit_after_reqnr, request.audit_limit
        )

    async def status(
        self, include_audit: bool = False, audit_after_reqnr: int = 0, audit_limit: int = 0
    ) -> drone_pb2.DroneStatus:
        """GetStatus without gRPC (``status.drone_status``)."""
        return await drone_status(self, include_audit, audit_after_reqnr, audit_limit)
