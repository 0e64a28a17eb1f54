"""The Drone gRPC service: Invoke for the master, Connect, Handover, GetStatus.

The drone executes one request at a time, in reqnr order, for the master
only (Section 4 of the paper). ``_lock`` is that single line of execution: a
request is checked and executed under it, and a handover takes it too, so a
switch always falls between two requests and every request is answered by
the master that was master when it was executed.
"""

from __future__ import annotations

import asyncio
import json
import sys
import time
from collections.abc import AsyncIterator, Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import grpc

from baton.digest import request_digest
from baton.drone.camera import DEFAULT_RESOLUTION, Camera
from baton.drone.dedupe import DEFAULT_WINDOW, CachedReply, ReplyCache
from baton.drone.dispatch import Dispatcher
from baton.drone.master import MasterSelection, ScriptedHandover
from baton.drone.mobility_api import MobilityBackend
from baton.drone.store import Counters, DroneStore, Intent
from baton.lifecycle import write_atomically
from baton.logs import get_logger
from baton.rpc.errors import StatusError, abort_with
from baton.rpc.server import BatonServer
from baton.stalls import StallWatch
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2, drone_pb2_grpc

# A status read must not hang on a vehicle that stopped answering.
_STATUS_READ_TIMEOUT_S = 1.0


async def latest_position(vehicle: MobilityBackend) -> api.Position:
    """The vehicle's position, or an all-zero Position if it is not known now."""
    if not vehicle.connected:
        return api.Position()
    try:
        reply = await asyncio.wait_for(
            vehicle.GetPosition(api.GetPositionRequest()), _STATUS_READ_TIMEOUT_S
        )
    except (StatusError, TimeoutError):
        return api.Position()
    return reply.position


# How far a new request number may be above the last one served. Numbers skip
# the Clock calls a controller answers itself, never this many; a larger jump
# is a bug or an attack, and accepting it (2**64 - 1, say) would make every
# later request look old, so the drone would refuse the mission for good.
MAX_REQNR_GAP = 1_000_000


def _retrieve_exception(task: asyncio.Task[Any]) -> None:
    """Marks a shielded request's failure as seen when its caller is gone (no asyncio warning)."""
    if not task.cancelled():
        task.exception()


class DroneService(drone_pb2_grpc.DroneServicer):
    """The drone middleware of drone.proto, over a vehicle backend and a camera."""

    def __init__(
        self,
        vehicle: MobilityBackend,
        camera: Camera,
        masters: MasterSelection,
        script: Mapping[int, ScriptedHandover] | None = None,
        cache_window: int = DEFAULT_WINDOW,
        race: Race | None = None,
        store: DroneStore | None = None,
    ) -> None:
        self.race = race
        self.store = store
        self._fired_script: list[int] = []
        self.vehicle = vehicle
        self.camera = camera
        self.masters = masters
        self.script = dict(script or {})  # pending scripted handovers, by reqnr
        self._handed_over_after = 0
        self.cache = ReplyCache(cache_window)
        self.dispatcher = Dispatcher({"Mobility": vehicle, "Camera": camera})
        self.last_reqnr = 0
        self.executed = 0
        self.duplicates = 0
        self.rejected = 0
        self.audit: list[drone_pb2.AuditEntry] = []
        self._lock = asyncio.Lock()
        self.log = get_logger("drone").bind(
            context=lambda: {"master": self.masters.master, "last_reqnr": self.last_reqnr}
        )
        self._stalls = StallWatch()
        self.waiting = ""
        if store is not None:
            self._restore(store)

    async def watch(self) -> None:
        """Every half second: stalls into GetStatus.waiting, and into the log when they begin."""
        while True:
            holding = {}
            if not self.masters.master_connected:
                holding["master"] = (
                    f"the master, controller {self.masters.master}, holds no Connect stream"
                )
            now = time.monotonic()
            stalls = self._stalls.update(now, holding)
            self.waiting = "; ".join(stalls)
            if self._stalls.due_for_log(now, stalls):
                self.log.warning("stalled", waiting=self.waiting)
            await asyncio.sleep(0.5)

    # -- durable state (store.py) ---------------------------------------------------

    def _counters(self) -> Counters:
        return Counters(
            master=self.masters.master,
            last_reqnr=self.last_reqnr,
            executed=self.executed,
            duplicates=self.duplicates,
            rejected=self.rejected,
            handovers=list(self.masters.handovers),
            fired_script=list(self._fired_script),
        )

    def _restore(self, store: DroneStore) -> None:
        """Resumes from the store: master, counters, replies, audit, script, a request cut off."""
        state = store.load()
        if state is None:
            store.save(self._counters())
            self.log.info("new state file", path=str(store.path))
            return
        c = state.counters
        self.masters.master = c.master
        self.masters.handovers[:] = c.handovers
        self.last_reqnr, self.executed = c.last_reqnr, c.executed
        self.duplicates, self.rejected = c.duplicates, c.rejected
        for reply in state.replies:
            self.cache.store(reply.reqnr, reply.method, reply.digest, reply.reply, reply.error)
        self.audit = state.audit
        self._fired_script = list(c.fired_script)
        for reqnr in c.fired_script:
            self.script.pop(reqnr, None)
        self.log.info(
            "state resumed",
            path=str(store.path),
            master=c.master,
            last_reqnr=c.last_reqnr,
            cached_replies=len(state.replies),
            audit=len(state.audit),
            script_left=len(self.script),
        )
        cut = state.executing
        if cut is None:
            return
        route = self.dispatcher.routes.get(cut.method)
        if route is not None and route.is_read:
            store.abandon()  # a read changed nothing: the re-sent request executes it again
            self.log.info("read cut off by the restart: will execute again", reqnr=cut.reqnr)
            return
        # The vehicle may have acted on it: at most once, so it is never executed again.
        error = StatusError(
            grpc.StatusCode.UNKNOWN,
            f"{cut.method} (request {cut.reqnr}) was being executed when the drone service "
            "restarted: the vehicle may have acted on it, so it is not executed again",
        )
        request = drone_pb2.InvokeRequest(
            controller_id=cut.controller_id, reqnr=cut.reqnr, method=cut.method
        )
        self.log.warning("request cut off by the restart", reqnr=cut.reqnr, method=cut.method)
        self._served(request, cut.digest, b"", cut.received_at, error)

    async def Invoke(
        self, request: drone_pb2.InvokeRequest, context: grpc.aio.ServicerContext
    ) -> drone_pb2.InvokeReply:
        """Executes one drone-API call for the master, or answers it from the reply cache."""
        received_at = time.time()
        try:
            return await self.invoke(request, received_at)
        except StatusError as err:
            self.rejected += 1
            self.log.warning(
                "invoke rejected",
                controller=request.controller_id,
                reqnr=request.reqnr,
                method=request.method,
                code=err.code.name,
                reason=err.message,
            )
            await abort_with(context, err)

    async def invoke(
        self, request: drone_pb2.InvokeRequest, received_at: float
    ) -> drone_pb2.InvokeReply:
        """Invoke without gRPC: the reply, or StatusError saying why not.

        Three kinds of failure: the protocol's rejections (not the master,
        wrong reqnr, a duplicate that differs) leave the reqnr unused and
        carry ``baton-master`` / ``baton-after-reqnr`` metadata; UNAVAILABLE
        (the vehicle not connected, no telemetry yet) means nothing was
        executed, so the reqnr stays unused too and the same request can be
        sent again; any other failure after the reqnr was accepted (bad
        method or payload, autopilot refusal, no acknowledgement in time) is
        served with that failure, which is cached and given again to a
        duplicate (see dedupe.py).

        A request runs to its end once it is received, whatever its caller
        does: it is a task of its own that the caller's cancellation (a
        deadline, a client that gave up) does not reach, so what the vehicle
        did is always recorded and a re-sent reqnr is answered from the
        cache, never executed again. A duplicate that arrives meanwhile
        waits for it (the lock) and gets its outcome.
        """
        task = asyncio.create_task(self._invoke_to_the_end(request, received_at))
        task.add_done_callback(_retrieve_exception)
        return await asyncio.shield(task)

    async def _invoke_to_the_end(
        self, request: drone_pb2.InvokeRequest, received_at: float
    ) -> drone_pb2.InvokeReply:
        cid, reqnr, method = request.controller_id, request.reqnr, request.method
        async with self._lock:
            if cid != self.masters.master:
                raise self.masters.not_master_error(cid, self.last_reqnr, f"Invoke reqnr {reqnr}")
            self.masters.note_request(cid, received_at)
            digest = request_digest(method, request.payload)
            cached = self.cache.get(reqnr)
            if cached is not None:
                return self._answer_duplicate(request, digest, cached)
            if reqnr <= self.last_reqnr:
                raise self._bad_reqnr(reqnr)
            if reqnr > self.last_reqnr + MAX_REQNR_GAP:
                raise StatusError(
                    grpc.StatusCode.FAILED_PRECONDITION,
                    f"reqnr {reqnr} is more than {MAX_REQNR_GAP} above the last one served "
                    f"({self.last_reqnr}): request numbers skip only the controller's own Clock "
                    "calls, and a number this far ahead would make every later request look "
                    "old; refused, nothing executed",
                    metadata=self._after_metadata(),
                )
            if self.store is not None:
                self.store.begin(Intent(reqnr, method, digest, cid, received_at))
            try:
                reply = await self._execute(request)
            except StatusError as err:
                if err.code is not grpc.StatusCode.UNAVAILABLE:
                    self._served(request, digest, b"", received_at, err)
                elif self.store is not None:
                    self.store.abandon()
                raise
            self._served(request, digest, reply, received_at)
        if (
            self.race is not None
            and self.race.order == "notice-first"
            and self._handed_over_after == reqnr
        ):
            await asyncio.sleep(self.race.delay_s)
        return drone_pb2.InvokeReply(reqnr=reqnr, payload=reply)

    def _answer_duplicate(
        self, request: drone_pb2.InvokeRequest, digest: bytes, cached: CachedReply
    ) -> drone_pb2.InvokeReply:
        if cached.digest != digest:
            raise StatusError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"reqnr {request.reqnr} was served as {cached.method} (request digest "
                f"{cached.digest.hex()[:16]}) but is re-sent as {request.method} (digest "
                f"{digest.hex()[:16]}): the mission program diverged",
                metadata=self._after_metadata(),
            )
        self.duplicates += 1
        self.log.info(
            "duplicate answered from cache",
            controller=request.controller_id,
            reqnr=request.reqnr,
            method=request.method,
            failed=cached.error is not None,
        )
        if cached.error is not None:
            raise StatusError(
                cached.error.code,
                cached.error.message,
                metadata=(*cached.error.metadata, ("baton-duplicate", "true")),
            )
        return drone_pb2.InvokeReply(reqnr=request.reqnr, payload=cached.reply, duplicate=True)

    def _after_metadata(self) -> tuple[tuple[str, str], ...]:
        return (
            ("baton-master", str(self.masters.master)),
            ("baton-after-reqnr", str(self.last_reqnr)),
        )

    def _bad_reqnr(self, reqnr: int) -> StatusError:
        # FAILED_PRECONDITION, not OUT_OF_RANGE: which numbers are acceptable
        # depends on the drone's state (the last reqnr served, what is still
        # cached), and the caller fixes it by resynchronising from the
        # metadata, not by changing a value that is wrong in itself. reqnr 0
        # can never be right, so it is INVALID_ARGUMENT.
        if reqnr == 0:
            return StatusError(
                grpc.StatusCode.INVALID_ARGUMENT, "reqnr 0 is not a request number; they start at 1"
            )
        oldest = self.cache.reqnrs[0] if len(self.cache) else None
        cached = f"; replies cached for reqnr {oldest}..{self.last_reqnr}" if oldest else ""
        return StatusError(
            grpc.StatusCode.FAILED_PRECONDITION,
            f"expected a reqnr above {self.last_reqnr} (or a cached duplicate), "
            f"got {reqnr}{cached}",
            metadata=self._after_metadata(),
        )

    async def _execute(self, request: drone_pb2.InvokeRequest) -> bytes:
        route = self.dispatcher.route(request.method)
        message = route.parse(request.payload)
        if route.service == "Mobility" and not self.vehicle.connected:
            raise StatusError(
                grpc.StatusCode.UNAVAILABLE,
                f"{request.method}: the vehicle at {self.vehicle.url} is not connected: "
                f"{self.vehicle.link().problem}",
            )
        handler = self.dispatcher.handler(route)
        try:
            reply = await handler(message)
        except StatusError:
            raise
        except Exception as exc:
            self.log.error("handler failed", method=request.method, exc_info=True)
            raise StatusError(
                grpc.StatusCode.INTERNAL, f"{request.method} failed on the drone: {exc!r}"
            ) from exc
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

    def _served(
        self,
        request: drone_pb2.InvokeRequest,
        digest: bytes,
        reply: bytes,
        received_at: float,
        error: StatusError | None = None,
    ) -> None:
        """Books a served request, then applies the script's handover after it."""
        reqnr = request.reqnr
        self.cache.store(reqnr, request.method, digest, reply, error)
        self.last_reqnr = reqnr
        # ``executed`` counts replies; a failed request counts as rejected
        # (in Invoke) but is audited, so the audit's reqnrs have no gaps.
        if error is None:
            self.executed += 1
        entry = drone_pb2.AuditEntry(
            reqnr=reqnr,
            method=request.method,
            controller_id=request.controller_id,
            received_at=received_at,
            reply_bytes=len(reply),
        )
        self.audit.append(entry)
        self._fire_script(reqnr)
        if self.store is not None:
            cached = self.cache.get(reqnr)
            assert cached is not None
            self.store.served(self._counters(), cached, entry, self.cache.reqnrs[0])

    def _fire_script(self, reqnr: int) -> None:
        """The handover script's line due after request ``reqnr``, if any."""
        # A scripted handover fires after the first request served at or past
        # its reqnr: request numbers the controllers answer themselves (Clock)
        # never reach the drone.
        due = [n for n in self.script if n <= reqnr]
        if not due:
            return
        scripted = self.script.pop(min(due))
        self._fired_script.append(min(due))
        if scripted.new_master == self.masters.master:
            self.log.warning(
                "scripted handover skipped: already the master",
                new_master=scripted.new_master,
                after_reqnr=reqnr,
                script_line=scripted.line,
            )
            return
        hold = self.race.delay_s if self.race and self.race.order == "reply-first" else 0.0
        self.masters.switch(scripted.new_master, reqnr, "script", notice_delay_s=hold)
        self._handed_over_after = reqnr

    async def Connect(
        self, request: drone_pb2.ConnectRequest, context: grpc.aio.ServicerContext
    ) -> AsyncIterator[drone_pb2.DroneEvent]:
        """The master's event stream: Connected, then a HandoverNotice at the switch."""
        cid = request.controller_id
        try:
            stream = self.masters.attach(cid, self.last_reqnr)
        except StatusError as err:
            self.log.warning("connect rejected", controller=cid, reason=err.message)
            await abort_with(context, err)
        self.log.info("master connected", controller=cid)
        try:
            if cid == self.masters.master:
                yield drone_pb2.DroneEvent(
                    connected=drone_pb2.Connected(master=cid, last_reqnr=self.last_reqnr)
                )
            while True:
                notice = self.masters.pending_notice(cid)
                if notice is not None:
                    yield drone_pb2.DroneEvent(handover=notice)
                    self.masters.delivered(cid, notice)
                    self.log.info(
                        "handover notice delivered",
                        controller=cid,
                        new_master=notice.new_master,
                        after_reqnr=notice.after_reqnr,
                    )
                    return
                if stream.superseded:
                    return
                await stream.wake.wait()
                stream.wake.clear()
        finally:
            self.masters.detach(stream)
            self.log.info("connect stream ended", controller=cid)

    async def Handover(
        self, request: drone_pb2.HandoverRequest, context: grpc.aio.ServicerContext
    ) -> drone_pb2.HandoverReply:
        """Switches the master after the request being served, if any.

        INVALID_ARGUMENT for an unknown id; FAILED_PRECONDITION if the id
        already is the master (not a silent no-op: a caller asking for a
        switch should learn that none happened).
        """
        try:
            self.masters.check_known(request.new_master)
            async with self._lock:
                record = self.masters.switch(request.new_master, self.last_reqnr, "rpc")
                if self.store is not None:
                    self.store.save(self._counters())
        except StatusError as err:
            self.log.warning("handover rejected", new_master=request.new_master, reason=err.message)
            await abort_with(context, err)
        return drone_pb2.HandoverReply(
            old_master=record.old_master,
            new_master=record.new_master,
            after_reqnr=record.after_reqnr,
        )

    async def GetStatus(
        self, request: drone_pb2.GetDroneStatusRequest, context: grpc.aio.ServicerContext
    ) -> drone_pb2.DroneStatus:
        """The drone's state, counters, handovers and (if asked) the command audit."""
        return await self.status(request.include_audit)

    async def status(self, include_audit: bool = False) -> drone_pb2.DroneStatus:
        """GetStatus without gRPC."""
        status = drone_pb2.DroneStatus(
            master=self.masters.master,
            last_reqnr=self.last_reqnr,
            executed=self.executed,
            duplicates=self.duplicates,
            rejected=self.rejected,
            vehicle_connected=self.vehicle.connected,
            vehicle_url=self.vehicle.url,
            position=await latest_position(self.vehicle),
            handovers=self.masters.handovers,
            master_connected=self.masters.master_connected,
            controllers=self.masters.controllers,
            vehicle=self.vehicle.link(),
            waiting=self.waiting,
        )
        if self.vehicle.connected:
            try:
                status.flight_state.CopyFrom(
                    await asyncio.wait_for(
                        self.vehicle.GetFlightState(api.GetFlightStateRequest()),
                        _STATUS_READ_TIMEOUT_S,
                    )
                )
            except (StatusError, TimeoutError):
                pass  # unknown now: left empty
        if include_audit:
            status.audit.extend(self.audit)
        return status


@dataclass(frozen=True)
class Race:
    """Forces footnote 2's race one way at scripted handovers (fault injection for tests).

    ``notice-first`` holds the reply of the request after which the drone
    hands over, so the old master gets the notice while its call is still in
    flight; ``reply-first`` holds the notice, so the reply is logged first.
    """

    order: str
    delay_s: float


@dataclass(frozen=True)
class DroneSettings:
    """Everything ``baton drone`` needs, from flags or the testbed configuration."""

    address: str = "127.0.0.1:50051"
    vehicle_url: str = "udpin://127.0.0.1:14540"
    controllers: tuple[int, ...] = (0,)
    initial_master: int | None = None
    handover_script: Mapping[int, ScriptedHandover] = field(default_factory=dict)
    image_file: str | None = None
    resolution: tuple[int, int] = DEFAULT_RESOLUTION
    speedup: float = 1.0
    cache_window: int = DEFAULT_WINDOW
    address_file: str | None = None
    race: Race | None = None
    state_file: str | None = None  # the durable state (store.py); None: memory only

    @property
    def master(self) -> int:
        """The initial master: given, else the first controller."""
        return self.initial_master if self.initial_master is not None else self.controllers[0]


def build_service(settings: DroneSettings, vehicle: MobilityBackend) -> DroneService:
    """The Drone servicer for ``settings`` over ``vehicle``."""

    async def position() -> api.Position:
        return await latest_position(vehicle)

    camera = Camera(position, settings.image_file, settings.resolution)
    masters = MasterSelection(settings.controllers, settings.master)
    store = DroneStore(settings.state_file) if settings.state_file else None
    return DroneService(
        vehicle,
        camera,
        masters,
        settings.handover_script,
        settings.cache_window,
        settings.race,
        store,
    )


async def serve(
    settings: DroneSettings,
    vehicle: MobilityBackend,
    stop: asyncio.Event,
    on_listening: Callable[[str], None] | None = None,
) -> int:
    """Runs the drone service until ``stop`` is set."""
    service = build_service(settings, vehicle)
    server = BatonServer(
        settings.address, [drone_pb2.DESCRIPTOR.services_by_name["Drone"].full_name]
    )
    drone_pb2_grpc.add_DroneServicer_to_server(service, server.server)
    await vehicle.start()
    await server.start()
    log = get_logger("drone")
    log.info(
        "listening",
        address=server.address,
        vehicle_url=vehicle.url,
        controllers=list(settings.controllers),
        master=settings.master,
        scripted_handovers=len(settings.handover_script),
        speedup=settings.speedup,
    )
    print(json.dumps({"event": "listening", "address": server.address}), flush=True)
    if settings.address_file:
        write_atomically(settings.address_file, server.address + "\n")
    if on_listening is not None:
        on_listening(server.address)
    watchdog = asyncio.create_task(service.watch(), name="stall-watchdog")
    try:
        await stop.wait()
    finally:
        watchdog.cancel()
        await server.stop()
        await vehicle.close()
        if service.store is not None:
            service.store.close()
        log.info("stopped", executed=service.executed, last_reqnr=service.last_reqnr)
    sys.stdout.flush()
    return 0
