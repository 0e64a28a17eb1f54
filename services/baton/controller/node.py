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
from typing import Any

import grpc

from baton.config import BatonConfig
from baton.controller.clock import MissionClock
from baton.controller.core import (
    CLOCK_NOW,
    CLOCK_SERVICE,
    Answer,
    Arm,
    AskClock,
    ControllerCore,
    CoreEffect,
    Disarm,
    Fail,
    Hold,
    Keep,
    KeepMastership,
    Note,
    Persist,
    Preparing,
    Reconnect,
    Rejoin,
    RepairGap,
    ReplayAgain,
    RingSight,
    RouteTo,
    Seen,
    SendCatchUp,
    SettleHandovers,
    Timer,
    to_retained,
)
from baton.controller.drone_link import (
    STOP_GRACE_S,
    DroneRefusal,
    DroneSession,
    DroneStandby,
    Retry,
    WarmChannel,
    refusal_of,
)
from baton.controller.history import LogHistory
from baton.controller.invoking import Sent, failed, replied
from baton.controller.link_core import SyncWord
from baton.controller.links import RingLinks
from baton.controller.notes import Handovers, note_of, replay_again
from baton.controller.protocol import (
    ConnectDrone,
    ControllerProtocol,
    DisconnectDrone,
    Fenced,
    SendLog,
    State,
    Unqueued,
)
from baton.controller.ring import PeerLink, Relay
from baton.controller.session_events import SessionEvents
from baton.controller.status import Sight, holding, recover
from baton.controller.timers import TimerTable
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
        self._changed = asyncio.Event()
        # The ring streams this controller keeps, by peer id.
        self.ring = RingLinks(self.history, lambda: self.protocol.successor, self._make_link)
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
        self.handovers = Handovers()
        self.t_conn_s: list[float] = []
        self.drone_connected_at: list[float] = []  # of closed connections (all_drone_...)
        # The standby stream: the drone's way to reach us for a takeover.
        self._standby = DroneStandby(
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
        await self._apply(recover(self.core, self.history, self.id))
        self._open_links()
        self._standby.start()
        await self._apply(self.protocol.start())
        self._warm_channel.start()
        self._watchdog = asyncio.create_task(self._watch(), name="stall-watchdog")
        self.log.info("controller started; asking the drone who the master is")

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
        drone, link = self._drone, self.ring.get(self.protocol.successor)
        sight = Sight(
            drone=None if drone is None else (drone.address, drone.connected.is_set()),
            standby_address=self._standby.address,
            standby_up=self._standby.up,
            in_flight=self._in_flight,
            operator_pause=drone.operator_pause if drone is not None else "",
            successor_link=None if link is None else (link.stream_up, link.unacked),
        )
        return holding(self.protocol, self.routed_around, sight)

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
        self._timers.close()
        if self._settler is not None:
            self._settler.cancel()
        await self._standby.stop()
        if self._drone is not None:
            await self._drone.close(grace=STOP_GRACE_S)
            self._drone = None
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
        self.incarnation += 1
        kept = self.core.kept_on_rejoin(self.history)
        fresh = self.core.fresh_self()
        await self._close_drone()
        for link in self.ring.drop_all():
            await link.stop()
        self.history.clear()
        self._timers.clear()
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
        await self._apply(
            self.core.prepare(
                prepare.target, prepare.epoch, prepare.timeout_s, prepare.bound_bytes, now
            )
        )

    def _preparation_progress(self) -> drone_pb2.PreparationProgress | None:
        """How far a prepared handover's target is behind us (``RingLinks.progress``)."""
        return self.ring.progress(self.core, time.monotonic())

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
            await self._apply(core.timer_fired(timer, time.monotonic(), self._sight()))

    def _ring_changed(self) -> None:
        """A ring stream came up, went down, or began to carry something while down
        (``ControllerCore.ring_changed``)."""
        self._background.spawn(self._route_now(), name="ring-changed")

    async def _route_now(self) -> None:
        await self._apply(self.core.ring_changed(time.monotonic(), self._sight()))

    def drone_streams_changed(self) -> None:
        """A stream to the drone broke: cut off from it, a queued message of a newer
        mastership fences us (``ControllerCore.ready``, told the drone's reach)."""
        self._background.spawn(self._apply([]), name="drone-streams")

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
            connected = self.drone_connected
            reachable = connected or self._standby.up
            ready = self.core.ready(effects, connected, time.monotonic(), reachable)
        except InvariantBroken as broken:
            # A defect of baton: stop as a kill -9 would, rather than go on.
            self.log.error("invariant broken; the controller stops", problem=str(broken))
            os._exit(INVARIANT_EXIT)
        for effect in ready:
            if isinstance(effect, Seen):
                # The program's answer, most effects of a replay: nothing to report or keep.
                self._seen(effect.entry)
                continue
            note = effect if isinstance(effect, Note) else note_of(effect, self.protocol.epoch)
            if note is not None:
                getattr(self.log, note.level)(note.text, **note.fields)
            self.handovers.take(effect, time.time())
            if isinstance(effect, Persist | Keep):
                self.ring.keep(effect.message)
            elif isinstance(effect, SendLog):
                link = self.peer(effect.dest)
                unused = not link.used
                link.send(effect.message)
                if unused and not link.stream_up:
                    self._ring_changed()  # a link down counts for the route once used
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
                self._fail(StatusError(effect.code, effect.text))
            elif isinstance(effect, SettleHandovers):
                self.ring.settle_handovers(self.protocol.handover_settled)
            elif isinstance(effect, RepairGap):
                if self.on_gap is not None:
                    self.on_gap()
            elif isinstance(effect, RouteTo):
                await self._routed(effect)
            elif isinstance(effect, Preparing):
                self.ring.preparing(effect.target)
            elif isinstance(effect, Arm | Disarm):
                self._timers.apply(effect)
            elif isinstance(effect, Fenced):
                self.fenced_messages += 1
            elif isinstance(effect, Unqueued):
                self.fenced_messages += 1
                self.ring.discard(effect.lognr, effect.epoch)
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
        events = SessionEvents(self, self._background)
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

    async def on_sync(self, from_id: int, word: SyncWord) -> None:
        """A ring stream's sync frame from controller ``from_id``: what it holds, and the
        newest ACTIVE master's word, as far as the core believes them
        (``ControllerCore.sync_arrived``)."""
        await self._apply(self.core.sync_arrived(from_id, word))

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
        """The program starts again from the log, its call ABORTED (``notes.replay_again``)."""
        self.program_restarts += 1
        note, aborted = replay_again(self.id, again, self.program_restarts)
        getattr(self.log, note.level)(note.text, **note.fields)
        raise StatusError(grpc.StatusCode.ABORTED, aborted)

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
        """Sends the request until it has an outcome (``invoking.failed``'s rules)."""
        retry = Retry(self.config.drone_retry_limit)
        while True:
            drone = self._drone
            if drone is None or self.protocol.state is not State.ACTIVE:
                return None
            if not drone.connected.is_set():
                await self._wait_connected(drone)
                continue
            sent = Sent(reqnr, method, request, digest, drone.epoch)
            try:
                self._in_flight = (reqnr, method)
                reply = await drone.invoke(
                    reqnr,
                    method,
                    request,
                    timeout_s=max(1.0, retry.limit_s - retry.waited()),
                    watermark_reqnr=self.protocol.watermark_reqnr,
                    master_answers=[to_retained(entry) for entry in self.core.answered_here],
                    preparation=self._preparation_progress(),
                    adopted_from_reqnr=self.core.adopted_from(),
                )
                return replied(sent, reply.payload, reply.epoch, reply.signature)
            except grpc.aio.AioRpcError as exc:
                detail, waited = exc.details() or "", retry.waited()
                outcome = failed(
                    self.core,
                    sent,
                    exc.code(),
                    detail,
                    refusal_of(exc),
                    waited,
                    retry.limit_s,
                    retry.attempts,
                )
            if outcome.pause is not None:
                self._drone_wait = Wait(
                    "retry", f"request {reqnr} ({method}): drone unavailable ({detail})", waited
                )
                if retry.should_log():
                    self.log.warning(
                        "drone unavailable; re-sending",
                        reqnr=reqnr,
                        waited_s=round(waited, 1),
                        limit_s=retry.limit_s,
                        detail=detail,
                    )
                retry.attempts += 1
                await asyncio.sleep(outcome.pause)
                continue
            if outcome.entry is None:  # a refusal: the core judged it
                await self._apply(outcome.effects)
            elif retry.attempts:
                self.log.warning(
                    "drone still unavailable; the call fails",
                    reqnr=reqnr,
                    waited_s=round(waited, 1),
                )
            return outcome.entry

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
