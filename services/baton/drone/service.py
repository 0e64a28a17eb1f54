"""The Drone gRPC service: Invoke for the master, Connect, Handover, GetStatus.

The drone executes one request at a time, in reqnr order, for the master
only (Section 4 of the paper). ``_lock`` is that single line of execution: a
request is checked and executed under it, and a handover takes it too, so a
switch always falls between two requests and every request is answered by
the master that was master when it was executed.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Iterable, Mapping
from typing import Any

import grpc

from baton.authenticity import Signer
from baton.drone.applier import Applier
from baton.drone.camera import Camera
from baton.drone.connects import ConnectStream
from baton.drone.core import WATCH_TICK_S, DroneCore
from baton.drone.dispatch import Dispatcher
from baton.drone.effects import DroneEffect, Preparing
from baton.drone.failsafe_watch import FailsafeWatch
from baton.drone.invariants import DroneWatch, checking
from baton.drone.invocations import Invocations
from baton.drone.link_probe import PING_PERIOD_S, LinkProbes
from baton.drone.master import MasterStreams, StandbyStreams
from baton.drone.mobility_api import MobilityBackend
from baton.drone.operator_service import OperatorCommands
from baton.drone.policy import LinkBounds, LinkState, Station
from baton.drone.policy_runner import PolicyRunner
from baton.drone.restore import VEHICLE_COMMAND_KEY, restore
from baton.drone.safety import SafetyParams
from baton.drone.sequencer import Sequencer
from baton.drone.settings import Race
from baton.drone.sight import DroneSight
from baton.drone.status import StallWatcher, drone_status
from baton.drone.store import DroneStore, Intent
from baton.logs import get_logger
from baton.rpc.errors import StatusError, abort_with
from baton.rpc.tls import OPERATOR, Identity, refused, refused_status
from baton.stalls import Wait, one_line
from baton.v1 import drone_pb2, drone_pb2_grpc


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
        self.saved_command: dict[str, Any] | None = None
        # Every controller's station: the landing points of nearest_station.
        self.stations: Mapping[int, Station] = stations or {}
        self.seq = sequencer
        self.streams = MasterStreams(sequencer)
        self.standby = StandbyStreams()
        # The core's effects carried out (applier.py).
        self.applier = Applier(self)
        self.dispatcher = Dispatcher({"Mobility": vehicle, "Camera": camera})
        self._lock = asyncio.Lock()
        # Invoke and InvokeStream: admitted, executed, booked (invocations.py).
        self.invocations = Invocations(self)
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
            restore(self, store)

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
            due = self.sight().takeover_due(self.core, time.time())
            if due is not None or self.seq.preparing is not None:
                async with self._lock:
                    # Asked again under the lock: a request may have come meanwhile.
                    where = self.policy.position if self.policy is not None else None
                    self.apply(self.sight().master_watch(self.core, time.time(), where))
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
        if kept != self.saved_command and self.store is not None:
            self.store.save_commanded(VEHICLE_COMMAND_KEY, kept)
            self.saved_command = kept

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
        up = self.sight().holders
        now, clock = time.time(), time.monotonic()
        links = {}
        for cid in self.seq.ring:
            down = 0.0
            if cid not in up:
                down = (self.core.down_for(cid, now) or 0.0) * speedup
            links[cid] = self.probes.state(cid, cid in up, down, clock)
        return links

    def sight(self) -> DroneSight:
        """The controllers as the watches see them now: who holds a standby or a Connect
        stream, the master's Connect stream, who is in range (``sight.DroneSight``)."""
        in_range = self.policy.in_range() if self.policy is not None else None
        holders = self.standby.reachable | self.streams.holders
        return DroneSight(holders, self.streams.master_connected, in_range)

    def apply(self, effects: Iterable[DroneEffect], notice_delay_s: float = 0.0) -> None:
        """Carries out the core's effects in their order (``Applier.apply``), under the lock."""
        self.applier.apply(effects, notice_delay_s)

    async def Invoke(
        self, request: drone_pb2.InvokeRequest, context: grpc.aio.ServicerContext
    ) -> drone_pb2.InvokeReply:
        """Executes one drone-API call for the master, or answers it from the reply cache."""
        try:
            return await self.invocations.for_caller(context, request, time.time())
        except StatusError as err:
            await abort_with(context, err)

    async def InvokeStream(  # type: ignore[override]  # writes with context.write
        self,
        calls: AsyncIterator[drone_pb2.InvokeCall],
        context: grpc.aio.ServicerContext,
    ) -> None:
        """Invoke's calls as messages on one stream (``Invocations.stream``)."""
        await self.invocations.stream(calls, context)

    async def invoke(
        self, request: drone_pb2.InvokeRequest, received_at: float
    ) -> drone_pb2.InvokeReply:
        """Invoke without gRPC (``Invocations.invoke``)."""
        return await self.invocations.invoke(request, received_at)

    def not_as(self, context: grpc.aio.ServicerContext, what: str, cid: int) -> StatusError | None:
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
            refusal = self.not_as(context, "Connect", cid)
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
        said = ConnectStream(cid, self.signer)
        try:
            grant, batches = said.opened(self.core, request)
            if grant is not None:
                yield drone_pb2.DroneEvent(connected=grant)
            for batch in batches:
                yield drone_pb2.DroneEvent(retained=drone_pb2.RetainedBatch(replies=batch))
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
            refusal = self.not_as(context, "Standby", cid)
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
                yield drone_pb2.StandbyEvent(take_over=owed)
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
        refusal = self.not_as(context, "AnswerPing", request.controller_id)
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
                    await self.applier.switch_seen.wait()
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
        refusal = self.not_as(context, "ReportPreparation", cid)
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
