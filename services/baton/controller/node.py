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
import contextlib
import hashlib
import os
import time
from collections.abc import Callable, Coroutine, Sequence
from dataclasses import dataclass, field
from typing import Any

import grpc

from baton.config import BatonConfig, gap_repair_s
from baton.controller.clock import MissionClock
from baton.controller.core import (
    CLOCK_NOW,
    CLOCK_SERVICE,
    Answer,
    AskClock,
    ControllerCore,
    CoreEffect,
    Fail,
    FirstNewCall,
    Hold,
    Keep,
    KeepMastership,
    Note,
    Persist,
    Preparing,
    Reconnect,
    Record,
    Rejoin,
    RepairGap,
    ReplayAgain,
    RouteTo,
    Seen,
    SendCatchUp,
    SettleHandovers,
    to_retained,
)
from baton.controller.drone_link import (
    STOP_GRACE_S,
    DroneRefusal,
    DroneSession,
    DroneStandby,
    WarmChannel,
    refusal_of,
)
from baton.controller.history import LogHistory
from baton.controller.protocol import (
    ConnectDrone,
    ControllerProtocol,
    DisconnectDrone,
    Diverged,
    Fenced,
    ProtocolError,
    SendLog,
    State,
    TookOver,
    Unqueued,
)
from baton.controller.ring import PeerLink, Relay
from baton.drone.invariants import INVARIANT_EXIT, InvariantBroken
from baton.logs import get_logger
from baton.rpc.errors import StatusError
from baton.rpc.tls import Tls
from baton.stalls import StallWatch, Wait, controller_judge, one_line
from baton.tasks import TaskSet
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2, ring_pb2

# A call that comes while the previous one is pending waits this long for it to end
# before it is refused as concurrent: a program that gave up on a call (its deadline,
# a cancelled stream) makes its next one at once, and that one can reach the
# controller first (on another stream or connection, in no fixed order).
BUSY_GRACE_S = 2.0
# Re-sending a request the drone could not take (drone unreachable, vehicle
# link down): the same reqnr, so the drone's duplicate detection keeps it
# safe, after a pause that doubles up to a cap, for the configuration's
# drone_retry_limit; the wait is logged at once and again every 5 s (stalls.py).
RETRY_FIRST_S, RETRY_MAX_S = 0.2, 2.0


@dataclass
class Retry:
    """Re-sending with back-off for at most ``limit_s`` (wall time)."""

    limit_s: float
    started: float = field(default_factory=time.monotonic)
    attempts: int = 0
    _log_watch: StallWatch = field(default_factory=lambda: StallWatch(threshold_s=0.0))

    def waited(self) -> float:
        """Seconds since the first try."""
        return time.monotonic() - self.started

    def exhausted(self) -> bool:
        """The limit has passed."""
        return self.waited() >= self.limit_s

    def should_log(self) -> bool:
        """True on the first retry and then every 5 s (StallWatch's rhythm)."""
        now = time.monotonic()
        waits = self._log_watch.update(now, {"retry": "drone unavailable"})
        return self._log_watch.due_for_log(now, waits)

    async def pause(self) -> None:
        """Waits before the next try: RETRY_FIRST_S, doubling up to RETRY_MAX_S."""
        delay = min(RETRY_MAX_S, RETRY_FIRST_S * 2**self.attempts)
        self.attempts += 1
        await asyncio.sleep(min(delay, max(0.0, self.limit_s - self.waited())))


@dataclass
class HandoverEvent:
    """A handover as this controller saw it, for the status and the report."""

    role: ring_pb2.HandoverRole.ValueType  # ControllerHandover.role
    peer: int
    lognr: int
    reqnr: int
    log_bytes: int
    at: float = field(default_factory=time.time)
    epoch: int = 0
    drone_after_reqnr: int = 0
    holds_reqnr: int = 0  # a taker's
    first_new_reqnr: int = 0  # a taker's first call beyond the retained replies
    first_new_at: float = 0.0


class ControllerNode:
    """One mission controller: Algorithm 1 plus its ring streams and drone connection."""

    def __init__(
        self,
        config: BatonConfig,
        cid: int,
        log_file: str | None = None,
        tls: Tls | None = None,
    ) -> None:
        self.config = config
        self.id = cid
        # This controller's certificate for its calls (mutual TLS); None: insecure.
        self.tls = tls
        self.mission_address = ""  # where its program calls (set by the app once served)
        # The protocol and this controller's decisions about its drone session.
        self.core = ControllerCore(
            ControllerProtocol(cid, config.ring_order, config.flush_limit),
            cut_through=config.ring.cut_through,
            max_sleep_s=config.safety.max_sleep,
        )
        # Every log message this controller holds: what it recovers after a
        # restart (with a file of its own) and gives a successor that restarts.
        self.history = LogHistory(log_file)
        self.clock = MissionClock(config.speedup)
        self.log = get_logger("controller").bind(context=self._log_context, id=cid)
        if config.mission_id is not None:  # a station's session: its lines name the mission
            self.log = self.log.bind(mission=config.mission_id)
        # Replaced on every change, so a waiter holds the event of the state it saw.
        self._changed = asyncio.Event()
        self._peers: dict[int, PeerLink] = {}
        # The highest log number sent straight to each handover target (_send_catch_up).
        # The stream to the target when the preparation began, and the acknowledgements
        # it had counted then (a stream opened since counts from 0: ``_route`` drops one).
        self._acked_before_prepare: tuple[PeerLink | None, int] = (None, 0)
        # The word to the drone on a prepared handover in flight (``_target_acked``).
        self._reporting: asyncio.Task[None] | None = None
        self._report_again = False
        # When a frame of each log number last arrived (``arriving``), the newest few.
        self._arriving: dict[int, float] = {}
        self._drone: DroneSession | None = None
        self._busy: str | None = None
        self._idle = asyncio.Event()  # set while no call is pending (``_busy`` None)
        self._idle.set()
        self._settler: asyncio.Task[None] | None = None  # for those left when the program ended
        self.mission: ring_pb2.MissionState.ValueType = ring_pb2.MISSION_STATE_NONE
        self.mission_error = ""
        # A request the drone could not take, being re-sent (see _invoke_drone).
        self._drone_wait: Wait | None = None
        # Waits the watchdog sees (stalls.py): a missing log message, a ring stream down.
        self._stalls = StallWatch()
        self._stalled: list[Wait] = []
        self._watchdog: asyncio.Task[None] | None = None
        self._in_flight: tuple[int, str] | None = None  # the request the drone has now
        self._failure: StatusError | None = None
        self._reply_chain = hashlib.sha256()
        self._drone_calls = 0
        self.handovers: list[HandoverEvent] = []
        self.t_conn_s: list[float] = []
        self.drone_connected_at: list[float] = []  # of closed connections (all_drone_...)
        # The standby stream: the drone's way to reach us for a takeover.
        self._standby = DroneStandby(
            cid, config.drone_address_for(cid), self.on_take_over, self.log, tls
        )
        # A channel to the drone connected in advance, for the next session.
        self._warm_channel = WarmChannel(config.drone_address_for(cid), tls)
        self._router: asyncio.Task[None] | None = None
        # What the node starts and does not await (rejoins, closing a replaced drone
        # session, the session's events), held until each ends.
        self._background = TaskSet()
        self.fenced_messages = 0  # log messages dropped from a fenced master
        # Times the program was restarted to replay a call it gave up on (_replay_again).
        self.program_restarts = 0
        # Bumped when the controller rejoins after being fenced: calls of the
        # mission program from before then are refused, not answered.
        self.incarnation = 0
        # Set by the app: stops the mission program, resets, starts it again.
        self.on_rejoin: Callable[[], Coroutine[Any, Any, None]] | None = None
        # Set by the app: ends every incoming ring stream (RingReceiver.drop_streams).
        self.on_gap: Callable[[], None] | None = None

    @property
    def answered_from_retained(self) -> int:
        """Calls a taker's program was answered from the drone's retained replies."""
        return self.core.answered_from_retained

    @property
    def routed_around(self) -> list[int]:
        """The successors the ring routes around now."""
        return self.core.routed_around

    @property
    def protocol(self) -> ControllerProtocol:
        """Algorithm 1's state machine (the core's)."""
        return self.core.protocol

    def _log_context(self) -> dict[str, object]:
        p = self.protocol
        return {"state": p.state.name, "reqnr": p.reqnr, "lognr": p.lognr}

    # -- life cycle -----------------------------------------------------------------

    async def start(self) -> None:
        """Recovers the log file, opens the stream to the successor, asks the drone."""
        self._recover()
        self._open_links()
        self._standby.start()
        await self._apply(self.protocol.start())
        self._warm_channel.start()
        self._watchdog = asyncio.create_task(self._watch(), name="stall-watchdog")
        self._router = asyncio.create_task(self._route_watch(), name="ring-router")
        self.log.info("controller started; asking the drone who the master is")

    def _recover(self) -> None:
        """Handles the messages the log file held, as if received: a restart with what it had.

        Their forwards are not sent: the successor says what it lacks when its
        stream opens, and is given that from the history.
        """
        lognrs = list(self.history.above(0))
        # The mastership whose log the file holds: told on Connect, so that the
        # drone fences it if a takeover gave that log up while we were down.
        self.protocol.epoch = self.history.mastership_epoch
        for lognr in lognrs:
            try:
                self.protocol.on_log(self.history.get(lognr))
            except ProtocolError as exc:
                self._fail(
                    StatusError(
                        grpc.StatusCode.DATA_LOSS,
                        f"controller {self.id}: log file {self.history.path}: {exc}",
                    )
                )
                return
        if lognrs:
            self.log.info(
                "recovered from the log file",
                path=str(self.history.path),
                messages=len(lognrs),
                up_to_lognr=self.protocol.lognr,
            )

    @property
    def waits(self) -> list[Wait]:
        """What the controller waits for, judged (stalls.py), for GetStatus."""
        return [self._drone_wait, *self._stalled] if self._drone_wait else self._stalled

    @property
    def waiting(self) -> str:
        """The waits that need a person, as one line; empty when none does."""
        return one_line(self.waits)

    def stall_conditions(self) -> dict[str, str]:
        """What holds now that would be a stall if it lasted (stalls.py)."""
        p = self.protocol
        holding = {}
        missing = p.missing_lognr
        if missing is not None and p.log_queue:
            holding["gap"] = (
                f"log message {missing} missing while {len(p.log_queue)} later ones "
                f"are queued (up to {max(p.log_queue)})"
            )
        elif missing is not None:
            holding["gap"] = (
                f"our handover message {missing} has not come back round, though we "
                f"handled up to {p.lognr}: our history lacks it"
            )
        drone = self._drone
        if drone is not None and not drone.connected.is_set():
            holding["drone"] = f"no Connect stream to the drone at {drone.address}"
        if not self._standby.up:
            holding["standby"] = (
                f"no standby stream to the drone at {self._standby.address}: the drone "
                "cannot make this controller master if the master is lost"
            )
        if p.master and not p.caught_up:
            holding["catch-up"] = (
                f"master by the drone's word (epoch {p.epoch}) but catching up with the ring: "
                + (
                    f"handled log message {p.lognr} of {p.catch_up_to}"
                    if p.catch_up_to is not None
                    else f"controller {p.predecessor} has not said what it holds"
                )
            )
        if self._in_flight is not None:
            reqnr, method = self._in_flight
            sent = f"request {reqnr} ({method}) sent, no answer yet"
            if drone is not None and drone.operator_pause:
                holding["paused"] = f"{sent}: it waits at the drone, {drone.operator_pause}"
            else:
                holding[f"request {reqnr}"] = sent
        link = self._peers.get(p.successor)
        if link is not None and not link.stream_up:
            holding["ring"] = (
                f"ring stream to controller {p.successor} down "
                f"({link.unacked} messages not acknowledged)"
            )
        if self.routed_around:
            skipped = ", ".join(str(cid) for cid in self.routed_around)
            holding["routed"] = (
                f"ring routed around controller {skipped} (unreachable) to controller {p.successor}"
            )
        return holding

    async def _watch(self) -> None:
        """Every half second: stalls into the status, and into the log when they begin."""
        while True:
            self.history.poll()  # a failed checkpoint is said within this period
            now = time.monotonic()
            judge = controller_judge(
                self.config.handover_policy.name != "none",
                self.protocol.master,
                self.config.prepare_timeout,
            )
            self._stalled = self._stalls.update(now, self.stall_conditions(), judge)
            if self._stalls.due_for_log(now, self._stalled):
                self.log.warning("stalled", waiting=one_line(self._stalled))
            await asyncio.sleep(0.5)

    async def stop(self) -> None:
        """Closes every stream."""
        if self._watchdog is not None:
            self._watchdog.cancel()
        if self._reporting is not None:
            self._reporting.cancel()
        if self._router is not None:
            self._router.cancel()
        if self._settler is not None:
            self._settler.cancel()
        await self._standby.stop()
        if self._drone is not None:
            await self._drone.close(grace=STOP_GRACE_S)
            self._drone = None
        await self._warm_channel.close()
        for link in self._peers.values():
            await link.stop()
        self.history.close()

    async def reset(self) -> None:
        """Forgets the log and the mission's progress and starts over as a replica.

        For a controller whose mastership the drone took over: what it
        logged and flushed beyond what left it is not the ring's (the new
        master got those replies from the drone, framed in its own log
        messages), so it keeps nothing and catches up from its predecessor
        like a controller restarted with nothing. Its mission program must
        be restarted with it (``on_rejoin``).
        """
        self.incarnation += 1
        kept = self.core.kept_on_rejoin(self.history)
        fresh = self.core.fresh_self()
        await self._close_drone()
        for link in self._peers.values():
            await link.stop()
        self._peers = {}
        self.history.clear()
        self.core = fresh
        if self._settler is not None:
            self._settler.cancel()
            self._settler = None
        self.mission, self.mission_error = ring_pb2.MISSION_STATE_NONE, ""
        self._failure = None
        self._drone_wait, self._in_flight, self._busy = None, None, None
        self._idle.set()
        self._reply_chain = hashlib.sha256()
        self._drone_calls = 0
        self._open_links()
        await self._apply(self.protocol.start())
        for message in kept:
            await self.on_log(message)
        self.log.info("rejoined as a replica with nothing; catching up from the ring")

    def _open_links(self) -> None:
        """Opens the stream to the successor, and to every other controller, kept open
        for a handover: the old master's handover message and the catch-up go on an
        open stream, not after a connection's set-up (docs/design.md, "The ring's
        forwarding"). Only the successor's carries anything until then."""
        self.peer(self.protocol.successor).start()
        for pid in self.config.ring_order:
            if pid != self.id:
                self.peer(pid).start()

    def peer(self, pid: int) -> PeerLink:
        """The kept stream to controller ``pid``, created on first use.

        A stream to the successor (or to the one we route to around a dead
        successor) carries the history: the receiver is given what it lacks.
        """
        link = self._peers.get(pid)
        if link is None:
            history = self.history if pid == self.protocol.successor else None
            link = PeerLink(
                self.id,
                pid,
                self.config.controller(pid).reach,
                self.log,
                history,
                self.tls,
                self.config.ring.frame_bytes,
                self.config.mission_id,
            )
            link.on_handover_acked = self._handover_acked
            link.on_acked = self._target_acked
            link.master_word = lambda: self.protocol.master_word
            self._peers[pid] = link
        return link

    def relay_for(self, head: ring_pb2.LogMessage, total_bytes: int) -> Relay | None:
        """Cut-through: the relay that passes a message on to our successor as its frames
        arrive, if the protocol would forward it (``ControllerProtocol.forward_dest``)."""
        if not self.config.ring.cut_through:
            return None
        dest = self.protocol.forward_dest(head)
        return None if dest is None else self.peer(dest).relay(head.lognr, total_bytes)

    def arriving(self, lognr: int) -> None:
        """A frame of message ``lognr`` arrived: it is on its way, not missing."""
        self._arriving[lognr] = time.monotonic()
        if len(self._arriving) > 64:
            del self._arriving[min(self._arriving)]

    def _send_catch_up(self, target: int) -> None:
        """What a handover's target may lack, straight to it (``ControllerCore.catch_up``)."""
        messages = self.core.catch_up(target, self.history)
        if messages is not None:
            link = self.peer(target)
            for message in messages:
                link.send(message)

    async def on_prepare(self, prepare: drone_pb2.PrepareHandover) -> None:
        """The drone plans a handover (``ControllerCore.prepare``)."""
        now = asyncio.get_running_loop().time()
        await self._apply(
            self.core.prepare(
                prepare.target, prepare.epoch, prepare.timeout_s, prepare.bound_bytes, now
            )
        )

    def _preparing(self, preparing: Preparing) -> None:
        """A preparation began: the stream to its target counts acknowledgements from
        now; its time is up at ``preparing.until`` (loop time)."""
        link = self.peer(preparing.target)
        self._acked_before_prepare = (link, link.counters.acked)
        loop = asyncio.get_running_loop()
        loop.call_at(preparing.until, self._preparation_over, preparing)

    def _preparation_over(self, preparing: Preparing) -> None:
        for effect in self.core.preparation_over(
            preparing.target, preparing.epoch, preparing.until
        ):
            if isinstance(effect, Note):
                getattr(self.log, effect.level)(effect.text, **effect.fields)

    def _preparation_progress(self) -> drone_pb2.PreparationProgress | None:
        """How far a prepared handover's target is behind us (``ControllerCore.progress``).
        Only the acknowledgements of the stream the count was taken on: a stream opened
        since (the ring routed back past the target) counts from 0."""
        target = self.protocol.preparing_for
        link = self._peers.get(target) if target is not None else None
        if link is None:
            return self.core.progress(None)
        before, acked = self._acked_before_prepare
        return self.core.progress(
            link.unacked_bytes,
            link.waiting_for_ack_s(time.monotonic()),
            link.counters.acked - (acked if link is before else 0),
        )

    def _target_acked(self, peer_id: int) -> None:
        """An acknowledgement from ``peer_id``: a word to the drone between requests if it
        is due (``ControllerCore.report_due``). One word in flight at a time; the latest
        state goes next."""
        if not self.core.report_due(peer_id, self._preparation_progress()):
            return
        self._report_again = True
        if self._reporting is None or self._reporting.done():
            self._reporting = asyncio.create_task(self._report_preparation(), name="prepared")

    async def _report_preparation(self) -> None:
        while self._report_again:
            self._report_again = False
            drone, progress = self._drone, self._preparation_progress()
            if drone is None or progress is None or not drone.connected.is_set():
                return
            try:
                moved = await drone.report_preparation(progress)
            except grpc.aio.AioRpcError as exc:
                # Only a word: the next Invoke carries it again.
                self.log.info("preparation word not heard", code=exc.code().name)
                return
            if moved:
                self.log.info("drone moves the master on our word", target=progress.target)
                return

    def _handover_acked(self, message: ring_pb2.LogMessage) -> None:
        """The new master acknowledged our handover message: it enters our history now.

        Not before (a history copy re-sent ahead of it would overtake it, and
        its new master would take the copy for a normal message), and not only
        when it comes back round: the ring may go on past it
        without giving it back to us (the new master handed over again before
        its stream to its successor carried it, or the message went to a
        controller that then rejoined and gave it on to a dead successor). Our
        hello counts it then (``holds_lognr``), so a predecessor never gives it
        again, and our history must hold it for our successor, or the
        successor misses its log number for good.
        """
        if message.lognr in self.history:
            return
        self.history.add(message)
        self.peer(self.protocol.successor).holds_changed()

    async def _route_watch(self) -> None:
        """Every 0.1 s: routes the ring around a successor down for the detection time,
        repairs a gap in what we received, and fences us on a queued message of a
        newer mastership once the drone is out of reach (``_fence_by_the_ring``)."""
        while True:
            await self._repair_gap()
            await self._route()
            went_on = self.protocol.went_on_in_queue()
            if went_on is not None:
                await self._fence_by_the_ring(went_on)
            await asyncio.sleep(0.1)

    async def _repair_gap(self) -> None:
        """A gap in what we received, repaired (``ControllerCore.gap_due``)."""
        repair_s = gap_repair_s(self.config.detection_s)
        missing = self.protocol.missing_lognr
        frames = self._arriving.get(missing) if missing is not None else None
        await self._apply(self.core.gap_due(time.monotonic(), repair_s, frames))

    async def _route(self) -> None:
        """Where the ring's messages go (``ControllerCore.route_due``); the links follow."""
        now = time.monotonic()

        def down_for(pid: int) -> float | None:
            link = self._peers.get(pid)
            return None if link is None or not link.used else link.down_for(now)

        await self._apply(
            self.core.route_due(down_for, self.config.detection_s, self.drone_connected)
        )

    async def _routed(self, route: RouteTo) -> None:
        """The ring now sends to ``route.successor``: its stream carries the history; the
        stream to a successor routed to before, and not skipped now, ends once it has
        nothing unacknowledged."""
        link = self.peer(route.successor)
        if not link.has_history:
            link.give_history(self.history)
            await link.stop()
        link.start()
        link.holds_changed()
        retired = route.retired
        old = None if retired is None else self._peers.get(retired)
        if retired is not None and old is not None and old.unacked == 0:
            await old.stop()
            del self._peers[retired]

    @property
    def peers(self) -> dict[int, PeerLink]:
        """Streams this controller keeps, by peer id."""
        return dict(self._peers)

    @property
    def standby_up(self) -> bool:
        """Whether the standby stream to the drone is up."""
        return self._standby.up

    @property
    def drone_connected(self) -> bool:
        """Whether the drone's Connect stream is up."""
        return self._drone is not None and self._drone.connected.is_set()

    @property
    def all_drone_connected_at(self) -> list[float]:
        """When the drone said connected (Unix seconds), every connection so far."""
        current = self._drone.connected_at if self._drone is not None else []
        return self.drone_connected_at + current

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

    async def _apply(self, effects: Sequence[CoreEffect]) -> None:
        try:
            ready = self.core.ready(effects, self.drone_connected)
        except InvariantBroken as broken:
            # A defect of baton: stop as a kill -9 would, rather than go on.
            self.log.error("invariant broken; the controller stops", problem=str(broken))
            os._exit(INVARIANT_EXIT)
        for effect in ready:
            if isinstance(effect, Persist):
                self.history.add(effect.message)
                self.peer(self.protocol.successor).holds_changed()
            elif isinstance(effect, SendLog):
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
            elif isinstance(effect, Diverged):
                self.log.warning(
                    "the ring's log differs from ours: a takeover framed the same replies in "
                    "messages of its own; rejoining as a replica",
                    mlognr=effect.lognr,
                    our_epoch=effect.ours_epoch,
                    ring_epoch=effect.ring_epoch,
                )
            elif isinstance(effect, Reconnect):
                await self._close_drone()
                self._open_drone()
            elif isinstance(effect, Rejoin):
                self._background.spawn(self._rejoin(), name="rejoin")
            elif isinstance(effect, SendCatchUp):
                self._send_catch_up(effect.target)
            elif isinstance(effect, Record):
                self.handovers.append(
                    HandoverEvent(
                        effect.role,
                        effect.other,
                        effect.lognr,
                        effect.reqnr,
                        effect.log_bytes,
                        epoch=effect.epoch,
                        drone_after_reqnr=effect.drone_after_reqnr,
                        holds_reqnr=effect.holds_reqnr,
                    )
                )
            elif isinstance(effect, Note):
                getattr(self.log, effect.level)(effect.text, **effect.fields)
            elif isinstance(effect, Fail):
                self._fail(StatusError(effect.code, effect.text))
            elif isinstance(effect, Seen):
                self._seen(effect.entry)
            elif isinstance(effect, Keep):
                self._held(effect.message)
            elif isinstance(effect, SettleHandovers):
                self._settle_handovers()
            elif isinstance(effect, FirstNewCall):
                takers = [h for h in self.handovers if h.role == ring_pb2.HANDOVER_ROLE_TAKER]
                if takers:
                    takers[-1].first_new_reqnr, takers[-1].first_new_at = effect.reqnr, time.time()
                self.log.info(
                    "first new call after the takeover",
                    reqnr=effect.reqnr,
                    method=effect.method,
                    epoch=effect.epoch,
                )
            elif isinstance(effect, RepairGap):
                if self.on_gap is not None:
                    self.on_gap()
            elif isinstance(effect, RouteTo):
                await self._routed(effect)
            elif isinstance(effect, Preparing):
                self._preparing(effect)
            elif isinstance(effect, Fenced):
                self.fenced_messages += 1
                self.log.warning(
                    "log message from a fenced master dropped",
                    mlognr=effect.lognr,
                    origin=effect.origin,
                    message_epoch=effect.epoch,
                    epoch=self.protocol.epoch,
                )
            elif isinstance(effect, Unqueued):
                self.fenced_messages += 1
                self.history.discard(effect.lognr, effect.epoch)
                # The successor may hold the same: our sync frame says the master's
                # word again (``ControllerProtocol.on_sync``).
                self.peer(self.protocol.successor).holds_changed()
                self.log.warning(
                    "queued log message of a replaced framing dropped",
                    mlognr=effect.lognr,
                    origin=effect.origin,
                    message_epoch=effect.epoch,
                )
            elif isinstance(effect, TookOver):
                self.handovers.append(
                    HandoverEvent(
                        ring_pb2.HANDOVER_ROLE_NEW,
                        effect.old_master,
                        effect.lognr,
                        effect.reqnr,
                        effect.message_bytes,
                    )
                )
                self.log.info("taking over as master", old_master=effect.old_master)
            elif isinstance(effect, KeepMastership):
                self.history.keep_mastership_epoch(effect.epoch)
        self._notify()

    def _notify(self) -> None:
        changed, self._changed = self._changed, asyncio.Event()
        changed.set()

    def _open_drone(self) -> None:
        if self._drone is not None:
            return
        address = self.config.drone_address_for(self.id)
        events = _SessionEvents(self, self._background)
        channel, warm = self._warm_channel.take()
        self._drone = DroneSession(
            self.id,
            address,
            channel,
            events,
            self.log,
            mastership_epoch=lambda: self.protocol.log_mastership_epoch,
            holds_reqnr=lambda: self.protocol.held_reqnr,
            given_up_epoch=lambda: self.protocol.given_up_epoch,
        )
        events.session = self._drone
        self._drone.open()
        self.log.info("connecting to the drone", drone=address, connected_in_advance=warm)

    async def _close_drone(self) -> None:
        drone, self._drone = self._drone, None
        if drone is not None:
            if drone.t_conn_s is not None:
                self.t_conn_s.append(drone.t_conn_s)
            self.drone_connected_at.extend(drone.connected_at)
            # Closing from inside the drone's own event task would cancel it
            # mid-callback; let it finish on its own.
            self._background.spawn(drone.close(), name="drone-close")

    # -- events -----------------------------------------------------------------------

    async def on_granted(
        self,
        session: DroneSession,
        epoch: int,
        retained_through: int = 0,
        takeover: bool = False,
        watermark_reqnr: int = 0,
        takeover_epoch: int = 0,
        grant: drone_pb2.Grant | None = None,
    ) -> None:
        """The drone's Connected event: this controller is master in ``epoch``
        (``ControllerCore.granted``)."""
        if session is not self._drone:
            return  # a session closed meanwhile
        await self._apply(
            self.core.granted(
                epoch, retained_through, takeover, watermark_reqnr, takeover_epoch, grant
            )
        )

    async def on_retained(
        self, session: DroneSession, replies: Sequence[drone_pb2.RetainedReply]
    ) -> None:
        """A batch of the replies the drone retains for us (``ControllerCore.retained_batch``)."""
        if session is not self._drone:
            return
        await self._apply(self.core.retained_batch(replies))

    async def on_take_over(self, event: drone_pb2.TakeOver) -> None:
        """The drone made us master by takeover (``ControllerCore.take_over``)."""
        await self._apply(
            self.core.take_over(
                event.old_master, event.epoch, event.after_reqnr, event.watermark_reqnr
            )
        )

    async def _rejoin(self) -> None:
        try:
            if self.on_rejoin is not None:
                await self.on_rejoin()
            else:
                await self.reset()
        finally:
            self.core.rejoining = False

    async def on_connect_refused(self, session: DroneSession, refusal: DroneRefusal) -> None:
        """Connect refused (``ControllerCore.connect_refused``)."""
        if session is not self._drone:
            return  # a session closed meanwhile
        await self._apply(self.core.connect_refused(refusal))

    async def on_stream_notice(
        self, session: DroneSession, notice: drone_pb2.HandoverNotice
    ) -> None:
        """A handover notice on the Connect stream (``ControllerCore.stream_notice``)."""
        if session is not self._drone:
            return
        await self._apply(
            self.core.stream_notice(
                notice.new_master,
                notice.after_reqnr,
                notice.epoch,
                notice.takeover,
                notice.grant if notice.HasField("grant") else None,
                notice.takeover_epoch,
            )
        )

    async def on_sync(
        self,
        from_id: int,
        holds_lognr: int,
        holds_epoch: int = 0,
        master_epoch: int = 0,
        master_lognr: int = 0,
    ) -> None:
        """A ring stream's sync frame: what its sender holds, and the epoch of its
        message with that number (a word of a framing a takeover replaced is not
        taken, ``ControllerProtocol.on_sync``), and the newest ACTIVE master's word
        (a queued message older than it above what it held is dropped).

        Only a stream that carries the history sends more than 0: the one
        from our predecessor, or from the one before a dead predecessor that
        routes around it; so any sender's word counts.
        """
        await self._apply(
            self.protocol.on_sync(holds_lognr, holds_epoch, master_epoch, master_lognr)
        )

    async def on_handover_notice(self, new_master: int, after_reqnr: int, epoch: int = 0) -> None:
        """The drone chose another master (``ControllerCore.handover_notice``)."""
        await self._apply(self.core.handover_notice(new_master, after_reqnr, epoch))

    async def on_log(self, message: ring_pb2.LogMessage, relayed_by: int = 0) -> None:
        """A log message from the ring or from an old master (``ControllerCore.log_arrived``),
        relayed by controller ``relayed_by`` (0: our own history)."""
        self.log.debug(
            "log message received",
            mlognr=message.lognr,
            origin=message.origin,
            sender=message.sender,
            handover=message.handover,
            entries=len(message.entries),
        )
        await self._apply(
            self.core.log_arrived(
                message, lambda: self.drone_connected or self.standby_up, relayed_by
            )
        )

    async def _fence_by_the_ring(self, message: ring_pb2.LogMessage | None) -> None:
        """``message`` shows our mastership went on without our log: fenced if we are cut
        off from the drone (``ControllerCore.went_on_without_us``). Asked on the
        message's arrival and, for one queued while a stream still looked up, every
        0.1 s (``_route_watch``)."""
        reachable = self.drone_connected or self.standby_up
        await self._apply(self.core.went_on_without_us(message, reachable))

    def _settle_handovers(self) -> None:
        """Our handover messages still unacknowledged whose role is settled (the ring
        went on past them) lose their flag and enter our history, as on an
        acknowledgement (``PeerLink.settle_handovers``): a receiver restarted with
        nothing must not take that role again."""
        for link in list(self._peers.values()):
            for message in link.settle_handovers(self.protocol.handover_settled):
                self._handover_acked(message)

    def _held(self, message: ring_pb2.LogMessage) -> None:
        """Keeps a received message in the history; the successor's link says what we hold."""
        self.history.add(message)
        link = self._peers.get(self.protocol.successor)
        if link is not None:
            link.holds_changed()

    async def mission_done(self, failed: bool, error: str) -> bool:
        """The local mission program ended; the master flushes its last entries."""
        self.mission = ring_pb2.MISSION_STATE_FAILED if failed else ring_pb2.MISSION_STATE_DONE
        if error:
            self.mission_error = self.mission_error or error
        effects = self.protocol.on_mission_done()
        await self._apply(effects)
        self.log.info("mission program ended", failed=failed, flushed=bool(effects))
        if self.core.abandoned and self._settler is None:
            # Its last call was given up while this replica waited: no next
            # call will settle it, so the entry is consumed here when it comes,
            # else it would hold REPLAY for ever.
            self._settler = asyncio.create_task(self._settle_after_the_end())
        return bool(effects)

    async def _settle_after_the_end(self) -> None:
        try:
            await self._settle_abandoned()
        except StatusError:
            pass  # the mission's failure, already recorded by _fail

    def _fail(self, error: StatusError) -> None:
        self._failure = error
        self.mission = ring_pb2.MISSION_STATE_FAILED
        self.mission_error = error.message
        self.log.error("mission stopped", error=error.message)
        self._notify()

    # -- the mission program's calls ----------------------------------------------

    async def call(
        self,
        method: str,
        request: bytes,
        gave_up: Callable[[], grpc.StatusCode] = lambda: grpc.StatusCode.CANCELLED,
    ) -> ring_pb2.LogEntry:
        """Answers one drone-API call of the local mission program.

        Returns the log entry whose reply (or status) the program must see.
        Raises StatusError when the call cannot be answered at all. If the
        program gives up on the call while the master is at it (a deadline,
        a cancellation: this coroutine is cancelled), the master logs that
        failure, ``gave_up()``'s code, as the call's outcome: it is what the
        program saw, so it is what every replica's program sees, and a new
        master answers it from the log instead of sending it again. The
        drone, which may have acted, finishes and records it either way.
        """
        if self._busy is not None:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(BUSY_GRACE_S):
                    await self._idle.wait()
        if self._busy is not None:
            raise StatusError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"controller {self.id}: concurrent call {method} while {self._busy} is pending; "
                "a mission program makes one drone call at a time",
            )
        self._busy = method
        self._idle.clear()
        incarnation = self.incarnation
        try:
            if self.mission == ring_pb2.MISSION_STATE_NONE:
                self.mission = ring_pb2.MISSION_STATE_RUNNING
            try:
                await self._settle_abandoned()
            except asyncio.CancelledError:
                if incarnation == self.incarnation:
                    self.core.gave_up(0, method, request, gave_up())
                raise
            return await self._answer(method, request, gave_up, incarnation)
        finally:
            if incarnation == self.incarnation:
                self._busy = None
                self._idle.set()

    async def _settle_abandoned(self) -> None:
        """Gives the log's entry to each call the program gave up on while this controller
        waited (``ControllerCore.settle``), waiting for the log or the drone's word."""
        while True:
            if self._failure is not None:
                raise self._failure
            changed = self._changed
            done, effects = self.core.settle()
            await self._apply_call(effects)
            if done:
                return
            await changed.wait()

    def _seen(self, entry: ring_pb2.LogEntry) -> None:
        """Counts the entry the protocol consumed (``Seen``) into the reply chain."""
        if not entry.method.startswith(CLOCK_SERVICE):
            self._drone_calls += 1
        self._reply_chain.update(
            entry.reqnr.to_bytes(8, "big")
            + entry.status_code.to_bytes(4, "big", signed=True)
            + hashlib.sha256(entry.reply).digest()
        )

    def _check_incarnation(self, incarnation: int) -> None:
        """ABORTED for a call of the mission program from before a rejoin."""
        if incarnation != self.incarnation:
            raise StatusError(
                grpc.StatusCode.ABORTED,
                f"controller {self.id} rejoined as a replica after a takeover: its mission "
                "program is restarted, and this call of the one before is not answered",
            )

    async def _answer(
        self,
        method: str,
        request: bytes,
        gave_up: Callable[[], grpc.StatusCode],
        incarnation: int,
    ) -> ring_pb2.LogEntry:
        """The program's call answered (``ControllerCore.answer``): from the log, the
        retained replies, the Clock or the drone, waiting for a change as it says."""
        while True:
            self._check_incarnation(incarnation)
            if self._failure is not None:
                raise self._failure
            changed = self._changed
            step, effects = self.core.answer(method, request)
            await self._apply_call(effects)
            if self._failure is not None:
                raise self._failure
            try:
                if isinstance(step, Answer):
                    return step.entry
                if isinstance(step, Hold):
                    await changed.wait()
                    continue
                if isinstance(step, AskClock):
                    reply = await self._clock_call(method, request)
                    entry: ring_pb2.LogEntry | None = ring_pb2.LogEntry(
                        reqnr=step.reqnr,
                        method=method,
                        reply=reply,
                        request_digest=step.digest,
                        request=request,
                    )
                else:
                    entry = await self._invoke_drone(step.reqnr, method, request, step.digest)
            except asyncio.CancelledError:
                if incarnation == self.incarnation:
                    reqnr = 0 if isinstance(step, Answer) else step.reqnr
                    given_up = self.core.gave_up(reqnr, method, request, gave_up())
                    await asyncio.shield(self._apply_call(given_up))
                raise
            if entry is None:
                continue  # the state changed: asked again
            logged, effects = self.core.logged(step.reqnr, entry)
            await self._apply_call(effects)
            if logged is not None:
                return logged

    async def _apply_call(self, effects: Sequence[CoreEffect]) -> None:
        """``_apply`` for the call path: a mission stopped (``Fail``) or a program that
        starts again (``ReplayAgain``) ends the call with its status. Nothing to apply
        wakes nobody: a call that waits must not wake itself."""
        if effects:
            await self._apply(effects)
        again = next((e for e in effects if isinstance(e, ReplayAgain)), None)
        if again is not None:
            self._replay_again(again)
        if self._failure is not None:
            raise self._failure

    def _replay_again(self, again: ReplayAgain) -> None:
        """The program gave up on a call that the master's program did not: it starts again
        from the log (``ReplayAgain``; the rejoin comes with it), its call ABORTED.

        A replica's program gives up on its own clock while it waits for the log (a
        deadline, a cancellation); the master's program may have had its reply. The
        program has run on an answer the mission never had, but a replica's program
        has acted on nothing: it is restarted and replays the log from the start, as
        Temporal retries a workflow task from its history.
        """
        entry, method, code = again.entry, again.method, again.code
        master_saw = "a reply" if entry.status_code == 0 else f"status {entry.status_code}"
        self.program_restarts += 1
        self.log.warning(
            "the mission program gave up on a call the master's program did not; it starts "
            "again and replays the log (a deadline on a drone call makes a mission "
            "non-deterministic: wait for the log instead)",
            reqnr=entry.reqnr,
            method=method,
            gave_up=code.name,
            master_saw=master_saw,
            restarts=self.program_restarts,
        )
        raise StatusError(
            grpc.StatusCode.ABORTED,
            f"controller {self.id}: the program gave up on request {entry.reqnr} ({method}, "
            f"{code.name}) but the master's program got {master_saw}: the program starts "
            "again and replays the log",
        )

    async def _clock_call(self, method: str, request: bytes) -> bytes:
        """Clock calls are answered here and logged like drone replies.

        Logging Sleep too means a new master replays the sleeps its
        predecessor already slept instead of sleeping them again; a sleep cut
        short by a handover is discarded like any reply in flight. They also
        go to the drone with the next drone call (``_answered_here``),
        which keeps them for a taker: after a takeover the lost master's
        Sleeps are not slept again and its times are read again the same
        (docs/design.md, "Takeover").
        """
        if method == CLOCK_NOW:
            return api.NowReply(unix_time_s=self.clock.now()).SerializeToString()
        await self.clock.sleep(api.SleepRequest.FromString(request).seconds)
        return api.SleepReply().SerializeToString()

    async def _invoke_drone(
        self, reqnr: int, method: str, request: bytes, digest: bytes
    ) -> ring_pb2.LogEntry | None:
        try:
            return await self._invoke_drone_retrying(reqnr, method, request, digest)
        finally:
            self._drone_wait = None
            self._in_flight = None

    async def _invoke_drone_retrying(
        self, reqnr: int, method: str, request: bytes, digest: bytes
    ) -> ring_pb2.LogEntry | None:
        retry = Retry(self.config.drone_retry_limit)
        while True:
            drone = self._drone
            if drone is None or self.protocol.state is not State.ACTIVE:
                return None
            if not drone.connected.is_set():
                await self._wait_connected(drone)
                continue
            sent_epoch = drone.epoch
            try:
                self._in_flight = (reqnr, method)
                budget = max(1.0, retry.limit_s - retry.waited())
                reply = await drone.invoke(
                    reqnr,
                    method,
                    request,
                    timeout_s=budget,
                    watermark_reqnr=self.protocol.watermark_reqnr,
                    master_answers=[to_retained(entry) for entry in self.core.answered_here],
                    preparation=self._preparation_progress(),
                    adopted_from_reqnr=self.core.adopted_from(),
                )
                return ring_pb2.LogEntry(
                    reqnr=reqnr,
                    method=method,
                    reply=reply.payload,
                    request_digest=digest,
                    request=request,
                    drone_epoch=reply.epoch,
                    drone_signature=reply.signature,
                )
            except grpc.aio.AioRpcError as exc:
                refusal = refusal_of(exc)
                if refusal is not None:
                    await self._apply(
                        self.core.request_refused(
                            sent_epoch, refusal, reqnr, method, exc.details() or ""
                        )
                    )
                    return None
                if exc.code() is grpc.StatusCode.UNAVAILABLE and not retry.exhausted():
                    # The drone could not be reached, or its vehicle is not
                    # connected: nothing was executed, so the same reqnr is
                    # re-sent (the drone left it unused).
                    self._drone_wait = Wait(
                        "retry",
                        f"request {reqnr} ({method}): drone unavailable ({exc.details()})",
                        retry.waited(),
                    )
                    if retry.should_log():
                        self.log.warning(
                            "drone unavailable; re-sending",
                            reqnr=reqnr,
                            waited_s=round(retry.waited(), 1),
                            limit_s=retry.limit_s,
                            detail=exc.details(),
                        )
                    await retry.pause()
                    continue
                if retry.attempts:
                    self.log.warning(
                        "drone still unavailable; the call fails",
                        reqnr=reqnr,
                        waited_s=round(retry.waited(), 1),
                    )
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


class _SessionEvents:
    """A drone session's events, handed to the node on its event loop with the session."""

    def __init__(self, node: ControllerNode, tasks: TaskSet) -> None:
        self._node = node
        self._tasks = tasks  # the node's: each event runs as a task of its own
        self.session: DroneSession | None = None

    def _run(self, event: Coroutine[Any, Any, None]) -> None:
        self._tasks.spawn(event, name="drone-event")

    def granted(self, connected: drone_pb2.Connected) -> None:
        assert self.session is not None
        self._run(
            self._node.on_granted(
                self.session,
                connected.epoch,
                connected.retained_through,
                connected.takeover,
                connected.watermark_reqnr,
                connected.takeover_epoch,
                connected.grant if connected.HasField("grant") else None,
            )
        )

    def retained(self, replies: Sequence[drone_pb2.RetainedReply]) -> None:
        assert self.session is not None
        # A task like granted's: tasks start in the order they are made, so the
        # batch is taken after the Connected event's on_granted began (and reset).
        self._run(self._node.on_retained(self.session, replies))

    def notice(self, notice: drone_pb2.HandoverNotice) -> None:
        assert self.session is not None
        self._run(self._node.on_stream_notice(self.session, notice))

    def prepare(self, prepare: drone_pb2.PrepareHandover) -> None:
        self._run(self._node.on_prepare(prepare))

    def refused(self, refusal: DroneRefusal) -> None:
        assert self.session is not None
        self._run(self._node.on_connect_refused(self.session, refusal))
