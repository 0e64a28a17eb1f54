"""The controller runtime: Algorithm 1's state machine wired to the network.

``ControllerNode`` owns one ``ControllerCore`` and carries out its effects
(``apply``): log messages go to ``PeerLink`` streams, the drone connection
opens and closes with the ACTIVE state, the timers the core arms are set on
the event loop. The local mission program's calls are ``program_calls.py``'s
(from the drone when ACTIVE, from the log in REPLAY, held while PASSIVE), what
it waits for ``watchdog.py``'s. All of it runs on one event loop, so the core
sees one event at a time: a drone reply and a handover notice that race
(footnote 2) are handled in whichever order they arrive, and both orders
give every replica the same reply (``ControllerCore.logged``).
"""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import Callable, Coroutine, Sequence
from typing import Any

import grpc

from baton.config import BatonConfig
from baton.controller.bookkeeping import Bookkeeping
from baton.controller.clock import MissionClock
from baton.controller.core import (
    ControllerCore,
    CoreEffect,
    Fail,
    Reconnect,
    Rejoin,
    RepairGap,
    RingSight,
    RouteTo,
    Seen,
    SendCatchUp,
    Timer,
)
from baton.controller.drone_link import (
    STOP_GRACE_S,
    DroneRefusal,
    DroneSession,
    DroneStandby,
    WarmChannel,
)
from baton.controller.history import LogHistory
from baton.controller.link_core import SyncWord
from baton.controller.links import RingLinks
from baton.controller.notes import Handovers, note_of
from baton.controller.program_calls import ProgramCalls
from baton.controller.protocol import (
    ConnectDrone,
    ControllerProtocol,
    DisconnectDrone,
    SendLog,
)
from baton.controller.ring import PeerLink, Relay
from baton.controller.session_events import SessionEvents
from baton.controller.status import recover
from baton.controller.timers import TimerTable
from baton.controller.watchdog import StallWatcher
from baton.drone.invariants import INVARIANT_EXIT, InvariantBroken
from baton.logs import get_logger
from baton.rpc.errors import StatusError
from baton.rpc.tls import Tls
from baton.stalls import Wait, one_line
from baton.tasks import TaskSet
from baton.v1 import drone_pb2, ring_pb2


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
            detection_s=config.detection_s,
        )
        # The deadlines the core armed (``Arm``), on the event loop's clock (monotonic).
        self._timers = TimerTable(
            lambda at, fire, *args: asyncio.get_running_loop().call_at(at, fire, *args),
            self._timer_due,
        )
        # Every log message this controller holds: what it recovers after a
        # restart (with a file of its own) and gives a successor that restarts.
        self.history = LogHistory(log_file)
        self.clock = MissionClock(config.speedup)
        self.log = get_logger("controller").bind(context=self._log_context, id=cid)
        if config.mission_id is not None:  # a station's session: its lines name the mission
            self.log = self.log.bind(mission=config.mission_id)
        # Replaced on every change, so a waiter holds the event of the state it saw.
        self.changed = asyncio.Event()
        # The ring streams this controller keeps, by peer id.
        self.ring = RingLinks(self.history, lambda: self.protocol.successor, self._make_link)
        # What the ring links, the history and the timers are told (as the simulation's).
        self.books = Bookkeeping(self.ring, self.history, self._timers, lambda: self.protocol)
        # The mission program's calls, and what it saw.
        self.program = ProgramCalls(self)
        # The word to the drone on a prepared handover in flight (``_target_acked``).
        self._reporting: asyncio.Task[None] | None = None
        self._report_again = False
        # When a frame of each log number last arrived (``arriving``), the newest few.
        self._arriving: dict[int, float] = {}
        self.drone: DroneSession | None = None  # the session while ACTIVE
        # What the controller waits for (stalls.py), judged every half second.
        self.watcher = StallWatcher(self)
        self._watchdog: asyncio.Task[None] | None = None
        self.handovers = Handovers()
        self.t_conn_s: list[float] = []
        self.drone_connected_at: list[float] = []  # of closed connections (all_drone_...)
        # The standby stream: the drone's way to reach us for a takeover.
        self.standby = DroneStandby(
            cid,
            config.drone_address_for(cid),
            self.on_take_over,
            self.log,
            tls,
            config.drone_identity,
            on_down=self.drone_streams_changed,
        )
        # A channel to the drone connected in advance, for the next session.
        self._warm_channel = WarmChannel(config.drone_address_for(cid), tls, config.drone_identity)
        # What the node starts and does not await (rejoins, closing a replaced drone
        # session, the session's events), held until each ends.
        self._background = TaskSet()
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
        await self.apply(recover(self.core, self.history, self.id))
        self._open_links()
        self.standby.start()
        await self.apply(self.protocol.start())
        self._warm_channel.start()
        self._watchdog = asyncio.create_task(self.watcher.run(), name="stall-watchdog")
        self.log.info("controller started; asking the drone who the master is")

    @property
    def waits(self) -> list[Wait]:
        """What the controller waits for, judged (stalls.py), for GetStatus."""
        drone_wait, stalled = self.program.drone_wait, self.watcher.stalled
        return [drone_wait, *stalled] if drone_wait else stalled

    @property
    def waiting(self) -> str:
        """The waits that need a person, as one line; empty when none does."""
        return one_line(self.waits)

    async def stop(self) -> None:
        """Closes every stream."""
        if self._watchdog is not None:
            self._watchdog.cancel()
        if self._reporting is not None:
            self._reporting.cancel()
        self._timers.close()
        self.program.stop()
        await self.standby.stop()
        if self.drone is not None:
            await self.drone.close(grace=STOP_GRACE_S)
            self.drone = None
        await self._warm_channel.close()
        for link in self.ring.links.values():
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
        self.program.reset()
        kept = self.core.kept_on_rejoin(self.history)
        fresh = self.core.fresh_self()
        await self._close_drone()
        for link in self.ring.drop_all():
            await link.stop()
        self.history.clear()
        self._timers.clear()
        self.core = fresh
        self._open_links()
        await self.apply(self.protocol.start())
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
        """The kept stream to controller ``pid``, created on first use (``RingLinks.peer``)."""
        return self.ring.peer(pid)

    def _make_link(self, pid: int, history: LogHistory | None) -> PeerLink:
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
        link.on_handover_acked = self.ring.handover_acked
        link.on_acked = self._target_acked
        link.on_up_down = self._ring_changed
        link.master_word = lambda: self.protocol.master_word
        link.master_proof = lambda: self.protocol.master_proof
        self._ring_changed()  # down from its start, until it comes up
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

    async def on_prepare(self, prepare: drone_pb2.PrepareHandover) -> None:
        """The drone plans a handover (``ControllerCore.prepare``)."""
        now = asyncio.get_running_loop().time()
        await self.apply(self.core.prepare(prepare, now))

    def preparation_progress(self) -> drone_pb2.PreparationProgress | None:
        """How far a prepared handover's target is behind us (``RingLinks.progress``)."""
        return self.ring.progress(self.core, time.monotonic())

    def _target_acked(self, peer_id: int) -> None:
        """An acknowledgement from ``peer_id``: a word to the drone between requests if it
        is due (``ControllerCore.report_due``). One word in flight at a time; the latest
        state goes next."""
        if not self.core.report_due(peer_id, self.preparation_progress()):
            return
        self._report_again = True
        if self._reporting is None or self._reporting.done():
            self._reporting = asyncio.create_task(self._report_preparation(), name="prepared")

    async def _report_preparation(self) -> None:
        while self._report_again:
            self._report_again = False
            drone, progress = self.drone, self.preparation_progress()
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

    # -- timers and what changes them ------------------------------------------------

    def _sight(self) -> RingSight:
        """What the core is given of the links when it decides the route or a gap."""
        return RingSight(self.ring.down_since(), self.drone_connected, self._arriving)

    def _timer_due(self, timer: Timer) -> None:
        """A deadline the core armed came (``ControllerCore.timer_fired``): given to the
        core that armed it, not to a fresh self that replaced it meanwhile."""
        core = self.core
        self._background.spawn(self._timer_fired(core, timer), name=f"timer-{timer.value}")

    async def _timer_fired(self, core: ControllerCore, timer: Timer) -> None:
        if core is self.core:
            await self.apply(core.timer_fired(timer, time.monotonic(), self._sight()))

    def _ring_changed(self) -> None:
        """A ring stream came up, went down, or began to carry something while down
        (``ControllerCore.ring_changed``)."""
        self._background.spawn(self._route_now(), name="ring-changed")

    async def _route_now(self) -> None:
        await self.apply(self.core.ring_changed(time.monotonic(), self._sight()))

    def drone_streams_changed(self) -> None:
        """A stream to the drone broke: cut off from it, a queued message of a newer
        mastership fences us (``ControllerCore.ready``, told the drone's reach)."""
        self._background.spawn(self.apply([]), name="drone-streams")

    async def _routed(self, route: RouteTo) -> None:
        """The ring now sends to ``route.successor``: its stream carries the history; the
        stream to a successor routed to before, and not skipped now, ends once it has
        nothing unacknowledged."""
        plan = self.ring.rerouted(route)
        if plan.needs_history:
            await plan.link.stop()
        plan.link.start()
        plan.link.holds_changed()
        if plan.retired is not None:
            await plan.retired.stop()

    @property
    def peers(self) -> dict[int, PeerLink]:
        """Streams this controller keeps, by peer id."""
        return dict(self.ring.links)

    @property
    def standby_up(self) -> bool:
        """Whether the standby stream to the drone is up."""
        return self.standby.up

    @property
    def drone_connected(self) -> bool:
        """Whether the drone's Connect stream is up."""
        return self.drone is not None and self.drone.connected.is_set()

    @property
    def all_drone_connected_at(self) -> list[float]:
        """When the drone said connected (Unix seconds), every connection so far."""
        current = self.drone.connected_at if self.drone is not None else []
        return self.drone_connected_at + current

    @property
    def all_t_conn_s(self) -> list[float]:
        """T_conn of every drone connection so far, the open one included."""
        current = self.drone.t_conn_s if self.drone is not None else None
        return self.t_conn_s + ([current] if current is not None else [])

    # -- effects --------------------------------------------------------------------

    async def apply(self, effects: Sequence[CoreEffect]) -> None:
        """Carries out the core's effects for one step, in ``ControllerCore.ready``'s
        order, and wakes whatever waits for a change."""
        try:
            connected = self.drone_connected
            reachable = connected or self.standby.up
            ready = self.core.ready(effects, connected, time.monotonic(), reachable)
        except InvariantBroken as broken:
            # A defect of baton: stop as a kill -9 would, rather than go on.
            self.log.error("invariant broken; the controller stops", problem=str(broken))
            os._exit(INVARIANT_EXIT)
        for effect in ready:
            if isinstance(effect, Seen):
                # The program's answer, most effects of a replay: nothing to report or keep.
                self.program.seen(effect.entry)
                continue
            note = note_of(effect, self.protocol.epoch)
            if note is not None:
                getattr(self.log, note.level)(note.text, **note.fields)
            self.handovers.take(effect, time.time())
            if self.books.apply(effect):
                continue
            if isinstance(effect, SendLog):
                if self.ring.send(effect.dest, effect.message):
                    self._ring_changed()
            elif isinstance(effect, ConnectDrone):
                self._open_drone()
            elif isinstance(effect, DisconnectDrone):
                await self._close_drone()
            elif isinstance(effect, Reconnect):
                await self._close_drone()
                self._open_drone()
            elif isinstance(effect, Rejoin):
                self._background.spawn(self._rejoin(), name="rejoin")
            elif isinstance(effect, SendCatchUp):
                self.ring.send_catch_up(self.core, effect.target)
            elif isinstance(effect, Fail):
                self.program.fail(StatusError(effect.code, effect.text))
            elif isinstance(effect, RepairGap):
                if self.on_gap is not None:
                    self.on_gap()
            elif isinstance(effect, RouteTo):
                await self._routed(effect)
        changed, self.changed = self.changed, asyncio.Event()
        changed.set()

    def _open_drone(self) -> None:
        if self.drone is not None:
            return
        address = self.config.drone_address_for(self.id)
        events = SessionEvents(self, self._background)
        channel, warm = self._warm_channel.take()
        self.drone = DroneSession(
            self.id,
            address,
            channel,
            events,
            self.log,
            connect_request=lambda: self.core.connect_request(),
        )
        events.session = self.drone
        self.drone.open()
        self.log.info("connecting to the drone", drone=address, connected_in_advance=warm)

    async def _close_drone(self) -> None:
        drone, self.drone = self.drone, None
        if drone is not None and not self.standby_up:
            self.drone_streams_changed()
        if drone is not None:
            if drone.t_conn_s is not None:
                self.t_conn_s.append(drone.t_conn_s)
            self.drone_connected_at.extend(drone.connected_at)
            # Closing from inside the drone's own event task would cancel it
            # mid-callback; let it finish on its own.
            self._background.spawn(drone.close(), name="drone-close")

    # -- events -----------------------------------------------------------------------

    async def on_granted(self, session: DroneSession, connected: drone_pb2.Connected) -> None:
        """The drone's Connected event: this controller is master in its epoch
        (``ControllerCore.granted``)."""
        if session is not self.drone:
            return  # a session closed meanwhile
        await self.apply(self.core.granted(connected))

    async def on_retained(
        self, session: DroneSession, replies: Sequence[drone_pb2.RetainedReply]
    ) -> None:
        """A batch of the replies the drone retains for us (``ControllerCore.retained_batch``)."""
        if session is not self.drone:
            return
        await self.apply(self.core.retained_batch(replies))

    async def on_take_over(self, event: drone_pb2.TakeOver) -> None:
        """The drone made us master by takeover (``ControllerCore.take_over``)."""
        await self.apply(self.core.take_over(event))

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
        if session is not self.drone:
            return  # a session closed meanwhile
        await self.apply(self.core.connect_refused(refusal))

    async def on_stream_notice(
        self, session: DroneSession, notice: drone_pb2.HandoverNotice
    ) -> None:
        """A handover notice on the Connect stream (``ControllerCore.stream_notice``)."""
        if session is not self.drone:
            return
        await self.apply(self.core.stream_notice(notice))

    async def on_sync(self, from_id: int, word: SyncWord) -> None:
        """A ring stream's sync frame from controller ``from_id``: what it holds, and the
        newest ACTIVE master's word, as far as the core believes them
        (``ControllerCore.sync_arrived``)."""
        await self.apply(self.core.sync_arrived(from_id, word))

    async def on_handover_notice(self, new_master: int, after_reqnr: int, epoch: int = 0) -> None:
        """The drone chose another master (``ControllerCore.handover_notice``)."""
        await self.apply(self.core.handover_notice(new_master, after_reqnr, epoch))

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
        await self.apply(
            self.core.log_arrived(
                message, lambda: self.drone_connected or self.standby_up, relayed_by
            )
        )
