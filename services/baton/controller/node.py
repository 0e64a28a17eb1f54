"""The controller runtime: Algorithm 1's state machine wired to the network.

``ControllerNode`` owns one ``ControllerProtocol`` and carries out its
effects: log messages go to ``PeerLink`` streams, the drone connection opens
and closes with the ACTIVE state. It answers the local mission program's
calls (``call``): from the drone when ACTIVE, from the log in REPLAY, and
holds them while PASSIVE. All of it runs on one event loop, so the protocol
sees one event at a time: a drone reply and a handover notice that race
(footnote 2) are handled in whichever order they arrive, and both orders
give every replica the same reply (see ``_invoke_drone``).
"""

from __future__ import annotations

import asyncio
import hashlib
import time
from dataclasses import dataclass, field

import grpc

from baton.config import BatonConfig
from baton.controller.clock import MissionClock
from baton.controller.drone_link import DroneSession, notice_from_rejection
from baton.controller.protocol import (
    ConnectDrone,
    ControllerProtocol,
    DisconnectDrone,
    Effect,
    NonDeterminismError,
    ProtocolError,
    SendLog,
    State,
    request_digest,
)
from baton.controller.ring import PeerLink
from baton.logs import get_logger
from baton.rpc.errors import StatusError
from baton.v1 import drone_api_pb2 as api
from baton.v1 import ring_pb2

CLOCK_SERVICE = "/baton.v1.Clock/"
CLOCK_SLEEP = "/baton.v1.Clock/Sleep"
CLOCK_NOW = "/baton.v1.Clock/Now"
# How long an ACTIVE controller keeps re-sending a request the drone could not
# be reached for (same reqnr, so the drone's duplicate detection keeps it safe).
DRONE_RETRY_S = 30.0


@dataclass
class HandoverEvent:
    """A handover as this controller saw it, for the status and the report."""

    role: str  # "old" (we handed over) or "new" (we took over)
    peer: int
    lognr: int
    reqnr: int
    log_bytes: int
    at: float = field(default_factory=time.time)


class ControllerNode:
    """One mission controller: Algorithm 1 plus its ring streams and drone connection."""

    def __init__(self, config: BatonConfig, cid: int) -> None:
        self.config = config
        self.id = cid
        self.protocol = ControllerProtocol(
            cid, config.ring_order, config.flush_limit, config.master_id
        )
        self.clock = MissionClock(config.speedup)
        self.log = get_logger("controller").bind(context=self._log_context, id=cid)
        # Replaced on every change, so a waiter holds the event of the state it saw.
        self._changed = asyncio.Event()
        self._peers: dict[int, PeerLink] = {}
        self._drone: DroneSession | None = None
        self._busy: str | None = None
        self.mission = "none"
        self.mission_error = ""
        self._failure: StatusError | None = None
        self._reply_chain = hashlib.sha256()
        self._drone_calls = 0
        self.handovers: list[HandoverEvent] = []
        self.t_conn_s: list[float] = []

    def _log_context(self) -> dict[str, object]:
        p = self.protocol
        return {"state": p.state.value, "reqnr": p.reqnr, "lognr": p.lognr}

    # -- life cycle -----------------------------------------------------------------

    async def start(self) -> None:
        """Opens the stream to the successor and, as the initial master, the drone connection."""
        self.peer(self.protocol.successor).start()
        await self._apply(self.protocol.start())
        self.log.info("controller started", master=self.protocol.master)

    async def stop(self) -> None:
        """Closes every stream."""
        if self._drone is not None:
            await self._drone.close()
            self._drone = None
        for link in self._peers.values():
            await link.stop()

    def peer(self, pid: int) -> PeerLink:
        """The kept stream to controller ``pid``, created on first use."""
        link = self._peers.get(pid)
        if link is None:
            link = PeerLink(self.id, pid, self.config.controller(pid).reach, self.log)
            self._peers[pid] = link
        return link

    @property
    def peers(self) -> dict[int, PeerLink]:
        """Streams this controller keeps, by peer id."""
        return dict(self._peers)

    @property
    def drone_connected(self) -> bool:
        """Whether the drone's Connect stream is up."""
        return self._drone is not None and self._drone.connected.is_set()

    @property
    def all_t_conn_s(self) -> list[float]:
        """T_conn of every drone connection so far, the open one included."""
        current = self._drone.t_conn_s if self._drone is not None else None
        return self.t_conn_s + ([current] if current is not None else [])

    @property
    def drone_calls(self) -> int:
        """Calls answered so far that went to the drone (not the Clock)."""
        return self._drone_calls

    @property
    def reply_chain(self) -> bytes:
        """SHA-256 chain over every reply the mission program has seen, in order."""
        return self._reply_chain.digest()

    # -- effects --------------------------------------------------------------------

    async def _apply(self, effects: list[Effect]) -> None:
        for effect in effects:
            if isinstance(effect, SendLog):
                self.peer(effect.dest).send(effect.message)
                self.log.debug(
                    "log message sent",
                    dest=effect.dest,
                    mlognr=effect.message.lognr,
                    entries=len(effect.message.entries),
                    handover=effect.message.handover,
                )
            elif isinstance(effect, ConnectDrone):
                self._open_drone()
            elif isinstance(effect, DisconnectDrone):
                await self._close_drone()
        self._notify()

    def _notify(self) -> None:
        changed, self._changed = self._changed, asyncio.Event()
        changed.set()

    def _open_drone(self) -> None:
        if self._drone is not None:
            return
        address = self.config.drone_address_for(self.id)
        self._drone = DroneSession(self.id, address, self._on_notice_threadsafe, self.log)
        self._drone.open()
        self.log.info("connecting to the drone", drone=address)

    async def _close_drone(self) -> None:
        drone, self._drone = self._drone, None
        if drone is not None:
            if drone.t_conn_s is not None:
                self.t_conn_s.append(drone.t_conn_s)
            # Closing from inside the drone's own event task would cancel it
            # mid-callback; let it finish on its own.
            asyncio.get_running_loop().create_task(drone.close())

    def _on_notice_threadsafe(self, new_master: int, after_reqnr: int) -> None:
        asyncio.get_running_loop().create_task(self.on_handover_notice(new_master, after_reqnr))

    # -- events -----------------------------------------------------------------------

    async def on_handover_notice(self, new_master: int, after_reqnr: int) -> None:
        """The drone chose another master (Algorithm 1, lines 24-29)."""
        if self.protocol.state is not State.ACTIVE:
            return
        log_bytes = self.protocol.log.size
        try:
            effects = self.protocol.on_handover_notice(new_master)
        except ProtocolError as exc:
            self.log.error("bad handover notice", error=str(exc))
            return
        self.handovers.append(
            HandoverEvent("old", new_master, self.protocol.lognr, self.protocol.reqnr, log_bytes)
        )
        self.log.info(
            "handing over",
            new_master=new_master,
            drone_after_reqnr=after_reqnr,
            log_bytes=log_bytes,
        )
        await self._apply(effects)

    async def on_log(self, message: ring_pb2.LogMessage) -> None:
        """A log message from the ring or from an old master (lines 30-47)."""
        was_master = self.protocol.master
        try:
            effects = self.protocol.on_log(message)
        except ProtocolError as exc:
            self._fail(StatusError(grpc.StatusCode.INTERNAL, f"controller {self.id}: {exc}"))
            return
        if self.protocol.master and not was_master:
            self._took_over(message)
        self.log.debug(
            "log message received",
            mlognr=message.lognr,
            origin=message.origin,
            sender=message.sender,
            handover=message.handover,
            entries=len(message.entries),
        )
        await self._apply(effects)

    def _took_over(self, message: ring_pb2.LogMessage) -> None:
        self.handovers.append(
            HandoverEvent(
                "new", message.sender, message.lognr, self.protocol.reqnr, message.ByteSize()
            )
        )
        self.log.info("taking over as master", old_master=message.sender)

    async def mission_done(self, failed: bool, error: str) -> bool:
        """The local mission program ended; the master flushes its last entries."""
        self.mission = "failed" if failed else "done"
        if error:
            self.mission_error = self.mission_error or error
        effects = self.protocol.on_mission_done()
        await self._apply(effects)
        self.log.info("mission program ended", failed=failed, flushed=bool(effects))
        return bool(effects)

    def _fail(self, error: StatusError) -> None:
        self._failure = error
        self.mission = "failed"
        self.mission_error = error.message
        self.log.error("mission stopped", error=error.message)
        self._notify()

    # -- the mission program's calls ----------------------------------------------

    async def call(self, method: str, request: bytes) -> ring_pb2.LogEntry:
        """Answers one drone-API call of the local mission program.

        Returns the log entry whose reply (or status) the program must see.
        Raises StatusError when the call cannot be answered at all.
        """
        if self._busy is not None:
            raise StatusError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"controller {self.id}: concurrent call {method} while {self._busy} is pending; "
                "a mission program makes one drone call at a time",
            )
        self._busy = method
        try:
            if self.mission == "none":
                self.mission = "running"
            entry = await self._answer(method, request)
            if not method.startswith(CLOCK_SERVICE):
                self._drone_calls += 1
            self._reply_chain.update(
                entry.reqnr.to_bytes(8, "big")
                + entry.status_code.to_bytes(4, "big", signed=True)
                + hashlib.sha256(entry.reply).digest()
            )
            return entry
        finally:
            self._busy = None

    async def _answer(self, method: str, request: bytes) -> ring_pb2.LogEntry:
        while True:
            if self._failure is not None:
                raise self._failure
            state = self.protocol.state
            if state is State.REPLAY:
                return await self._replay(method, request)
            if state is State.ACTIVE:
                entry = await self._invoke(method, request)
                if entry is not None:
                    return entry
                continue
            await self._changed.wait()

    async def _replay(self, method: str, request: bytes) -> ring_pb2.LogEntry:
        try:
            entry, effects = self.protocol.replay(method, request)
        except NonDeterminismError as exc:
            self._fail(
                StatusError(grpc.StatusCode.FAILED_PRECONDITION, f"controller {self.id}: {exc}")
            )
            raise self._failure or StatusError(grpc.StatusCode.INTERNAL, str(exc)) from None
        await self._apply(effects)
        return entry

    async def _invoke(self, method: str, request: bytes) -> ring_pb2.LogEntry | None:
        """One call while ACTIVE: to the drone (or the clock), logged. None: state changed."""
        reqnr = self.protocol.reqnr + 1
        digest = request_digest(method, request)
        if method in (CLOCK_NOW, CLOCK_SLEEP):
            entry = ring_pb2.LogEntry(
                reqnr=reqnr,
                method=method,
                reply=await self._clock_call(method, request),
                request_digest=digest,
                request=request,
            )
        else:
            entry_or_none = await self._invoke_drone(reqnr, method, request, digest)
            if entry_or_none is None:
                return None
            entry = entry_or_none
        if self.protocol.state is not State.ACTIVE or self.protocol.reqnr + 1 != reqnr:
            # A handover notice overtook the reply (footnote 2): the reply is not
            # ours to log. The new master re-sends reqnr and the drone answers
            # it from its reply cache, so the program still sees this reply.
            self.log.info("reply discarded after handover", discarded_reqnr=reqnr)
            return None
        await self._apply(self.protocol.on_reply(entry))
        return entry

    async def _clock_call(self, method: str, request: bytes) -> bytes:
        """Clock calls are answered here and logged like drone replies.

        Logging Sleep too means a new master replays the sleeps its
        predecessor already slept instead of sleeping them again; a sleep cut
        short by a handover is discarded like any reply in flight.
        """
        if method == CLOCK_NOW:
            return api.NowReply(unix_time_s=self.clock.now()).SerializeToString()
        await self.clock.sleep(api.SleepRequest.FromString(request).seconds)
        return api.SleepReply().SerializeToString()

    async def _invoke_drone(
        self, reqnr: int, method: str, request: bytes, digest: bytes
    ) -> ring_pb2.LogEntry | None:
        deadline = time.monotonic() + DRONE_RETRY_S
        while True:
            drone = self._drone
            if drone is None or self.protocol.state is not State.ACTIVE:
                return None
            if not drone.connected.is_set():
                await self._wait_connected(drone)
                continue
            try:
                reply = await drone.invoke(reqnr, method, request)
                return ring_pb2.LogEntry(
                    reqnr=reqnr,
                    method=method,
                    reply=reply.payload,
                    request_digest=digest,
                    request=request,
                )
            except grpc.aio.AioRpcError as exc:
                notice = notice_from_rejection(exc)
                if notice is not None and notice[0] == self.id:
                    # The drone knows us as master yet refused the request
                    # number: the log and the drone disagree. Stop, loudly.
                    self._fail(
                        StatusError(
                            grpc.StatusCode.INTERNAL,
                            f"controller {self.id}: the drone refused request {reqnr} "
                            f"({method}): {exc.details()}",
                        )
                    )
                    return None
                if notice is not None:
                    await self.on_handover_notice(*notice)
                    return None
                if exc.code() is grpc.StatusCode.UNAVAILABLE and time.monotonic() < deadline:
                    # The drone could not be reached (or the vehicle is not
                    # connected yet): re-send the same reqnr, which is safe.
                    self.log.warning("drone unavailable; retrying", detail=exc.details())
                    await asyncio.sleep(0.2)
                    continue
                return ring_pb2.LogEntry(
                    reqnr=reqnr,
                    method=method,
                    request_digest=digest,
                    request=request,
                    status_code=exc.code().value[0],
                    status_message=exc.details() or "",
                )

    async def _wait_connected(self, drone: DroneSession) -> None:
        waiters = {
            asyncio.create_task(drone.connected.wait()),
            asyncio.create_task(self._changed.wait()),
        }
        try:
            await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for waiter in waiters:
                waiter.cancel()
