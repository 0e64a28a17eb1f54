"""One simulated mission controller: a driver of the shipped controller cores.

``SimController`` drives what ``controller/node.py``'s ``ControllerNode``
drives, with the asyncio taken out: ``ControllerCore`` (and its
``ControllerProtocol``), the ring links' ``RingLinks`` and ``LinkCore``
(through ``sim/network.py``'s ``RingLink``), ``status.recover`` and
``status.holding``, ``notes.note_of`` for what an effect says and
``bookkeeping.Bookkeeping`` for the effects on the ring links, the history
and the timers; each program call runs the same ``call_flow.CallFlow`` as
``ProgramCalls``. It owns only the virtual I/O: the drone session, what a
call's flow asks for, and the timers.

How asyncio maps onto events: node.py's ``changed`` event (set on every
``apply``) becomes ``_notify``, which schedules one ``_pump`` on the next
turn of the loop, and the pump wakes a flow that waits for a change. A
Sleep, a pause before a re-send and the drone's answer are events of
their own.

Simplifications: the drone session's events run at once where node.py
posts them as tasks; the stall watchdog and the logging are left out (its
waits go into the liveness report, ``holding``); a program call's deadline
is modelled only as the explicit give-up fault (``give_up``), not as gRPC
deadlines on drone calls (the retry limit, node.py's ``drone_retry_limit``,
is far beyond any fault).
"""

from __future__ import annotations

from collections.abc import Generator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import grpc

from baton.controller.bookkeeping import Bookkeeping
from baton.controller.call_flow import (
    Apply,
    CallFlow,
    Invoke,
    Invoked,
    Io,
    LookAtSession,
    Pause,
    ReadClock,
    SessionSeen,
    WaitConnected,
    WaitForChange,
)
from baton.controller.core import (
    CLOCK_NOW,
    ControllerCore,
    CoreEffect,
    DroneRefusal,
    Fail,
    Note,
    Reconnect,
    Rejoin,
    RepairGap,
    ReplayAgain,
    RingSight,
    RouteTo,
    Seen,
    SendCatchUp,
    Timer,
)
from baton.controller.history import LogHistory
from baton.controller.link_core import SyncWord
from baton.controller.links import RingLinks
from baton.controller.notes import note_of, replay_again
from baton.controller.protocol import (
    ConnectDrone,
    ControllerProtocol,
    DisconnectDrone,
    ProtocolError,
    SendLog,
    State,
)
from baton.controller.status import Sight, holding, recover
from baton.controller.timers import TimerTable
from baton.rpc.errors import StatusError
from baton.sim.drone import Request
from baton.sim.mission import MissionCall
from baton.sim.network import DroneLink, RingLink
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2, ring_pb2

if TYPE_CHECKING:
    from baton.sim.world import World

# BatonConfig.drone_retry_limit's default: how long UNAVAILABLE is re-sent.
DRONE_RETRY_LIMIT_S = 300.0
# DroneSession._follow_events's reconnect back-off.
SESSION_BACKOFF_FIRST_S, SESSION_BACKOFF_MAX_S = 0.05, 1.0
# Clock.Now answers in Unix time; the mission starts here.
MISSION_START_UNIX = 1.8e9


@dataclass(eq=False)
class Turn:
    """The program's call being answered (``call_flow.CallFlow``), and what its flow
    waits for; ``call`` None: the calls given up before the program ended, settled."""

    call: MissionCall | None
    flow: CallFlow
    steps: Generator[Io, object, ring_pb2.LogEntry | None]
    io: Io | None = None
    call_id: int = 0  # an Invoke on its way or being executed, and its connection
    connection: int = 0
    pauses: int = 0


@dataclass(eq=False)
class Session:
    """One ACTIVE period's drone session (drone_link.DroneSession)."""

    sid: int
    epoch: int = 0
    connected: bool = False
    closed: bool = False  # _close_drone: its events are no longer followed
    ended: bool = False  # _follow_events returned (a notice or a refusal)
    stream: int | None = None  # the connection its Connect stream is on
    waiting: bool = False  # a Connect waiting for the channel
    backoff: float = SESSION_BACKOFF_FIRST_S


class SimController:
    """A controller incarnation: protocol, history, ring links, drone session, mission program.

    A restart is a new incarnation with nothing (a fresh protocol, history
    and program); the killed one keeps what its program saw, for the oracles.
    """

    def __init__(self, world: World, cid: int, incarnation: int) -> None:
        self.world = world
        self.id = cid
        self.incarnation = incarnation
        self.alive = True
        # The shipped core: the protocol and the decisions about the drone session.
        self.core = ControllerCore(
            ControllerProtocol(cid, world.ring, world.flush_limit),
            world.cut_through,
            detection_s=world.detection_s,
        )
        # The deadlines the core armed (``Arm``), on the virtual clock.
        self._timers = TimerTable(world.loop.at, self._timer_due)
        if world.keys is not None:  # ControllerApp: its key seals, the ring's keys check
            self.core.keys = world.keys.keys
            self.core.protocol.seal = world.keys.controllers[cid].seal
        # The simulation checks the masterships after every event and reports the
        # event that broke them (invariant mastership-legal); the core does not stop.
        self.core.checking = False
        self.history = LogHistory()
        # The ring links (the shipped RingLinks, as ControllerNode's).
        self.ring = RingLinks(
            self.history,
            lambda: self.protocol.successor,
            lambda pid, history: RingLink(world, self, pid, history),
        )
        # What the ring links, the history and the timers are told (as ControllerNode's).
        self.books = Bookkeeping(self.ring, self.history, self._timers, lambda: self.protocol)
        self.drone_link = DroneLink(world, self)
        self.session: Session | None = None
        # The mission program: the next call, the current one, and where it is.
        self.program = world.program
        self.pc = 0
        self.turn: Turn | None = None  # the call being answered
        self.failure: str | None = None
        self.program_failed = False
        # What the protocol consumed (ProgramCalls.seen) and what the program saw, in order.
        self.seen: list[tuple[int, int, bytes]] = []
        self.view: list[tuple[int, bytes]] = []
        self.done_at: float | None = None
        self.peak_log_queue = 0
        # Handover messages it sent: (lognr, new master).
        # Whether the drone has answered its start-up question (granted, refused, a notice).
        self.answered = False
        self._pump_due = False
        self.accepted_upto = 0  # calls consumed before its last request the drone accepted
        self.ended_by = ""  # "rejoin" or "lost": how a failover ended this incarnation
        # The drone's last request when this incarnation died (None: alive): what it
        # consumed above it was decided where it ran (``oracles._observed``).
        self.drone_last_at_death: int | None = None

    # -- life cycle (ControllerNode.start / stop) ---------------------------------

    @property
    def routed_around(self) -> list[int]:
        """The successors the ring routes around now (the core's)."""
        return self.core.routed_around

    @property
    def protocol(self) -> ControllerProtocol:
        """Algorithm 1's state machine (the core's)."""
        return self.core.protocol

    def start(self) -> None:
        """Opens the stream to the successor and asks the drone (node.py start)."""
        recovered = recover(self.core, self.history, self.id)  # a history held: none yet
        if recovered:
            self._apply(recovered)
        self.peer(self.protocol.successor).start()
        self._apply(self.protocol.start())

    def begin_program(self) -> None:
        """Starts the mission program."""
        self._schedule_call()

    def kill(self, why: str = "killed") -> None:
        """The process dies with everything it held."""
        self.alive = False
        self.drone_last_at_death = self.world.drone.seq.last_reqnr
        self.world.trace(f"controller {self.id} {why}")
        self.drone_link.break_("controller killed")
        for other in self.world.live_controllers():
            link = other.links.get(self.id)
            if link is not None:
                link.break_("peer killed")
        self.history.close()

    def close(self) -> None:
        """Frees the history file at the end of a run."""
        if self.alive:
            self.history.close()

    @property
    def links(self) -> dict[int, RingLink]:
        """The ring links, by peer id."""
        return self.ring.links

    def peer(self, pid: int) -> RingLink:
        """ControllerNode.peer (``RingLinks.peer``)."""
        return self.ring.peer(pid)

    # -- effects (ControllerNode.apply) -------------------------------------------

    def _apply(self, effects: Sequence[CoreEffect]) -> None:
        session = self.session
        connected = session is not None and session.connected
        ready = self.core.ready(effects, connected, self.world.loop.now, self._drone_reachable())
        for effect in ready:
            note = note_of(effect, self.protocol.epoch)
            if note is not None and note.level != "debug":
                self._say(note)
            if self.books.apply(effect):
                continue
            if isinstance(effect, SendLog):
                message = effect.message
                self.world.by_origin.setdefault(message.origin, set()).add(message.lognr)
                self.world.framings.setdefault(message.lognr, set()).add(message.epoch)
                if self.ring.send(effect.dest, message):
                    self.ring_changed()
            elif isinstance(effect, ConnectDrone):
                self._open_drone()
            elif isinstance(effect, DisconnectDrone):
                self._close_drone()
            elif isinstance(effect, Reconnect):
                self._close_drone()
                self._open_drone()
            elif isinstance(effect, Rejoin):
                self._rejoin()
            elif isinstance(effect, SendCatchUp):
                for message in self.ring.send_catch_up(self.core, effect.target):
                    self.world.trace(
                        f"controller {self.id} sends {message.lognr} straight to {effect.target}"
                    )
            elif isinstance(effect, Fail):
                self._fail(effect.text)
            elif isinstance(effect, Seen):
                self._seen(effect.entry)
            elif isinstance(effect, ReplayAgain):
                self._replayed_again(effect)
            elif isinstance(effect, RepairGap):
                self.world.drop_streams_to(self)
            elif isinstance(effect, RouteTo):
                self._routed(effect)
        self.world.after_apply(self, effects)
        self._notify()

    def _say(self, note: Note) -> None:
        """A Note into the trace (the runtime logs it)."""
        fields = " ".join(f"{k}={v}" for k, v in note.fields.items())
        self.world.trace(f"controller {self.id}: {note.text} ({fields})")

    def _notify(self) -> None:
        """The end of ControllerNode.apply: wakes what waits for a change, on the next turn."""
        if not self._pump_due:
            self._pump_due = True
            self.world.loop.after(0.0, self._pump)

    def _pump(self) -> None:
        """The node's change wakes a flow waiting for it (``WaitForChange``, ``WaitConnected``);
        a program that ended with calls given up while waiting settles them."""
        self._pump_due = False
        if not self.alive:
            return
        turn = self.turn
        if turn is None:
            if self.done and self.core.abandoned:  # ProgramCalls.mission_done's settler
                flow = CallFlow(self.core, "", b"", DRONE_RETRY_LIMIT_S)
                self._run(Turn(None, flow, flow.settle()))
            return
        if isinstance(turn.io, WaitForChange | WaitConnected):
            self._advance(turn, None)

    def _fail(self, text: str) -> None:
        """ProgramCalls.fail: the mission stops on this controller."""
        if self.failure is None:
            self.failure = text
            self.world.trace(f"controller {self.id} FAILED: {text}")
        self._notify()

    # -- the drone session (ControllerNode._open_drone / _close_drone, DroneSession) --

    def _open_drone(self) -> None:
        if self.session is not None:
            return
        session = Session(self.world.next_id())
        self.session = session
        self._connect(session)

    def _close_drone(self) -> None:
        session, self.session = self.session, None
        if session is None:
            return
        session.closed = True
        link = self.drone_link
        if session.stream == link.generation and link.usable():
            link.to_drone(0, self.world.drone.receive_stream_closed, self.id, session.sid)

    def _connect(self, session: Session) -> None:
        """DroneSession._follow_events: one Connect, waiting for the channel if it is down."""
        if not self.alive or session is not self.session or session.ended:
            return
        if session.stream is not None or session.waiting:
            return
        link = self.drone_link
        if not link.usable():
            session.waiting = True
            link.when_usable(self._channel_ready, session)
            return
        session.stream = link.generation
        request = self.core.connect_request()
        link.to_drone(
            0, self.world.drone.receive_connect, link, session.sid, link.generation, request
        )

    def _channel_ready(self, session: Session) -> None:
        session.waiting = False
        self._connect(session)

    def _reconnect_later(self, session: Session) -> None:
        session.stream, session.connected = None, False
        self.world.loop.after(session.backoff, self._connect, session)
        session.backoff = min(session.backoff * 2, SESSION_BACKOFF_MAX_S)
        self.drone_streams_changed()

    def on_drone_connected(self, sid: int, connected: drone_pb2.Connected) -> None:
        """The Connected event (``ControllerCore.granted``)."""
        session = self.session
        if session is None or session.sid != sid:
            return
        session.epoch, session.connected = connected.epoch, True
        self._startup_answer()
        try:
            effects = self.core.granted(connected)
        except ProtocolError as exc:
            self._uncaught("on_granted", exc)
            return
        self._apply(effects)

    def on_drone_retained(self, sid: int, replies: list[drone_pb2.RetainedReply]) -> None:
        """A RetainedBatch event: node.py's on_retained."""
        session = self.session
        if session is None or session.sid != sid:
            return
        self._apply(self.core.retained_batch(replies))

    def on_drone_notice(self, sid: int, notice: drone_pb2.HandoverNotice) -> None:
        """A HandoverNotice on the stream, which then ends (``ControllerCore.stream_notice``)."""
        session = self.session
        if session is None or session.sid != sid:
            return
        session.ended, session.stream = True, None
        self._startup_answer()
        self._apply(self.core.stream_notice(notice))

    def on_drone_prepare(self, sid: int, prepare: drone_pb2.PrepareHandover) -> None:
        """A PrepareHandover event on the stream (``ControllerCore.prepare``)."""
        session = self.session
        if session is None or session.sid != sid:
            return
        self._apply(self.core.prepare(prepare, self.world.loop.now))

    def on_drone_refused(self, sid: int, error: StatusError) -> None:
        """Connect refused: node.py's on_connect_refused if it names a master, else reconnect."""
        session = self.session
        if session is None or session.sid != sid:
            return
        refusal = DroneRefusal.of_status(error.code, dict(error.metadata))
        if refusal is None:
            self._reconnect_later(session)
            return
        session.ended, session.stream = True, None
        self._startup_answer()
        self.on_connect_refused(refusal)

    def _startup_answer(self) -> None:
        if not self.answered:
            self.answered = True
            self.world.check_start()

    def on_drone_stream_ended(self, sid: int) -> None:
        """The drone ended the stream without a notice (superseded): reconnect."""
        session = self.session
        if session is not None and session.sid == sid:
            self._reconnect_later(session)

    def on_drone_link_broken(self, connection: int) -> None:
        """The connection broke: the call in flight fails UNAVAILABLE, the stream reconnects."""
        if not self.alive:
            return
        turn = self.turn
        if turn is not None and turn.call_id and turn.connection == connection:
            error = StatusError(grpc.StatusCode.UNAVAILABLE, "connection to the drone lost")
            self._invoked(turn, None, error)
        session = self.session
        if session is not None and session.stream == connection:
            self._reconnect_later(session)
        else:
            self.drone_streams_changed()

    # -- events (ControllerNode.on_*) ---------------------------------------------

    def _uncaught(self, where: str, exc: ProtocolError) -> None:
        """A ProtocolError that node.py does not catch there: the controller is broken."""
        self._fail(f"controller {self.id}: ProtocolError escapes node.py {where}: {exc}")

    def on_connect_refused(self, refusal: DroneRefusal) -> None:
        """ControllerNode.on_connect_refused."""
        self._apply(self.core.connect_refused(refusal))

    def on_take_over(self, event: drone_pb2.TakeOver) -> None:
        """The standby stream's TakeOver (``ControllerCore.take_over``)."""
        if self.alive:
            self._apply(self.core.take_over(event))

    def _rejoin(self) -> None:
        """A rejoin as ControllerApp.rejoin does it (the program stops, reset, incoming
        streams dropped, the program starts again), as a restart with nothing."""
        self.world.loop.after(0.0, self.world.rejoin, self)

    # -- timers and what changes them (ControllerNode's) ---------------------------

    def _sight(self) -> RingSight:
        """ControllerNode._sight (the simulation's messages arrive whole: no frames)."""
        session = self.session
        connected = session is not None and session.connected
        return RingSight(self.ring.down_since(), connected)

    def _timer_due(self, timer: Timer) -> None:
        """ControllerNode._timer_due (``ControllerCore.timer_fired``)."""
        if self.alive:
            self._apply(self.core.timer_fired(timer, self.world.loop.now, self._sight()))

    def ring_changed(self) -> None:
        """ControllerNode._ring_changed: decided on the next turn, as the node's task."""
        if self.alive:
            self.world.loop.after(0.0, self._route_now)

    def _route_now(self) -> None:
        if self.alive:
            self._apply(self.core.ring_changed(self.world.loop.now, self._sight()))

    def drone_streams_changed(self) -> None:
        """ControllerNode.drone_streams_changed (the standby stream is up exactly while
        the link is usable here)."""
        if self.alive:
            self._apply([])

    def _routed(self, route: RouteTo) -> None:
        """ControllerNode._routed: the new successor's stream carries the history."""
        plan = self.ring.rerouted(route)
        if plan.needs_history:
            plan.link.restart()
        plan.link.start()
        plan.link.holds_changed()
        if plan.retired is not None:
            plan.retired.stop()
        self.world.check_start()

    def on_sync(self, from_id: int, word: SyncWord) -> None:
        """ControllerNode.on_sync (``ControllerCore.sync_arrived``)."""
        if not self.alive:
            return
        try:
            effects = self.core.sync_arrived(from_id, word)
        except ProtocolError as exc:
            self._uncaught("on_sync", exc)
            return
        self._apply(effects)

    def on_handover_notice(self, new_master: int, after_reqnr: int, epoch: int = 0) -> None:
        """ControllerNode.on_handover_notice (Algorithm 1, lines 24-29)."""
        self._apply(self.core.handover_notice(new_master, after_reqnr, epoch))

    # -- a prepared handover (docs/design.md, "Prepared handover") ----------------

    def _preparation_progress(self) -> drone_pb2.PreparationProgress | None:
        """ControllerNode.preparation_progress (``RingLinks.progress``)."""
        return self.ring.progress(self.core, self.world.loop.now)

    def on_log(self, message: ring_pb2.LogMessage) -> None:
        """ControllerNode.on_log (``ControllerCore.log_arrived``)."""
        if not self.alive:
            return
        self.world.check_overtaken_handover(self, message)
        effects = self.core.log_arrived(message, self._drone_reachable)
        self.peak_log_queue = max(self.peak_log_queue, len(self.protocol.log_queue))
        self._apply(effects)

    def receive_relayed(self, message: ring_pb2.LogMessage, relayed_by: int) -> None:
        """A whole log message on a ring stream from ``relayed_by`` (a lying station's
        frame, lying.py): ``ControllerCore.log_arrived``, as ``on_log``."""
        if not self.alive:
            return
        self._apply(self.core.log_arrived(message, self._drone_reachable, relayed_by))

    def _drone_reachable(self) -> bool:
        """Either stream to the drone up (the standby stream is up exactly while the link
        is usable here)."""
        session = self.session
        return (session is not None and session.connected) or self.drone_link.usable()

    def target_acked(self, peer_id: int) -> None:
        """ControllerNode._target_acked: a target within the drone's bound is reported
        between requests (ReportPreparation). Every such ack sends a word here, where
        node.py keeps one in flight and sends the latest next: each word stands alone,
        so these interleavings include its."""
        if not self.alive:
            return
        progress = self._preparation_progress()
        if progress is None or not self.core.report_due(peer_id, progress):
            return
        session, link = self.session, self.drone_link
        if session is None or not session.connected or not link.usable():
            return
        self.world.trace(f"controller {self.id} reports {progress.lacks_bytes} B to the drone")
        link.to_drone(
            progress.ByteSize(), self.world.drone.receive_report, self.id, session.epoch, progress
        )

    def handover_acked(self, message: ring_pb2.LogMessage) -> None:
        """PeerLink.on_handover_acked (``RingLinks.handover_acked``)."""
        self.ring.handover_acked(message)

    # -- the mission program: its calls' flows (call_flow.CallFlow) ----------------

    def _schedule_call(self) -> None:
        if self.pc < len(self.program):
            think = self.world.rng.uniform(0.0, 0.02)
            self.world.loop.after(think, self._begin_call, self.pc)

    def _begin_call(self, pc: int) -> None:
        if not self.alive or self.pc != pc or self.turn is not None or self.program_failed:
            return
        call = self.program[pc]
        flow = CallFlow(self.core, call.method, call.request, DRONE_RETRY_LIMIT_S)
        self._run(Turn(call, flow, flow.run()))

    def _run(self, turn: Turn) -> None:
        self.turn = turn
        self._advance(turn, None)

    def _advance(self, turn: Turn, result: object) -> None:
        """Sends ``result`` to the turn's flow and carries out what it yields, up to a wait
        (``ProgramCalls._drive`` and ``_perform``, on the virtual clock and network)."""
        while self.alive and self.turn is turn:
            if self.failure is not None:
                self._stop()
                return
            turn.io, turn.call_id = None, 0
            try:
                io = turn.steps.send(result)
            except StopIteration as stop:
                self._answered(turn, stop.value)
                return
            turn.io, result = io, None
            if isinstance(io, Apply):
                self._apply(io.effects)
            elif isinstance(io, LookAtSession):
                session = self.session
                connected = session is not None and session.connected
                epoch = session.epoch if session is not None else 0
                result = SessionSeen(session is not None, connected, epoch, self.world.loop.now)
            elif isinstance(io, ReadClock) and io.method == CLOCK_NOW:
                result = api.NowReply(unix_time_s=MISSION_START_UNIX + self.world.loop.now)
                result = result.SerializeToString()
            elif isinstance(io, ReadClock):
                seconds = api.SleepRequest.FromString(io.request).seconds
                self.world.loop.after(seconds, self._slept, turn, io)
                return
            elif isinstance(io, Invoke):
                self._send(turn, io)
                return
            elif isinstance(io, Pause):
                turn.pauses += 1
                self.world.loop.after(io.seconds, self._paused, turn, turn.pauses)
                return
            elif isinstance(io, WaitForChange | WaitConnected):
                return  # woken by _pump
            # RetriesEnded: logged by the runtime; nothing to do here

    def _slept(self, turn: Turn, io: ReadClock) -> None:
        if turn.io is io:
            self._advance(turn, api.SleepReply().SerializeToString())

    def _paused(self, turn: Turn, pauses: int) -> None:
        if isinstance(turn.io, Pause) and turn.pauses == pauses:
            self._advance(turn, None)

    def _send(self, turn: Turn, io: Invoke) -> None:
        """DroneSession.invoke: with wait_for_ready, the call waits for the channel."""
        if not self.alive or self.turn is not turn or turn.io is not io:
            return
        link = self.drone_link
        if not link.usable():
            link.when_usable(self._send, turn, io)
            return
        turn.call_id, turn.connection = self.world.next_id(), link.generation
        sent = io.sent
        request = Request(
            self.id,
            sent.epoch,
            sent.reqnr,
            sent.method,
            sent.request,
            turn.call_id,
            link,
            link.generation,
            carried=self.core.carried(self._preparation_progress()),
            sender=self,
            consumed=len(self.seen),
        )
        link.to_drone(len(sent.request), self.world.drone.receive_invoke, request)

    def on_invoke_reply(
        self, call_id: int, reply: drone_pb2.InvokeReply | None, error: StatusError | None
    ) -> None:
        """The drone's answer to an Invoke (a reply, a refusal, a failure)."""
        turn = self.turn
        if turn is not None and turn.call_id == call_id:  # else one the program gave up on
            self._invoked(turn, reply, error)

    def _invoked(
        self, turn: Turn, reply: drone_pb2.InvokeReply | None, error: StatusError | None
    ) -> None:
        now = self.world.loop.now
        if error is None:
            assert reply is not None
            self._advance(turn, Invoked(now, (reply.payload, reply.epoch, reply.signature)))
            return
        refusal = DroneRefusal.of_status(error.code, dict(error.metadata))
        self._advance(turn, Invoked(now, None, error.code, error.message, refusal))

    def _seen(self, entry: ring_pb2.LogEntry) -> None:
        """ProgramCalls.seen: the entries the protocol consumed, in order (the reply chain)."""
        self.seen.append((entry.reqnr, entry.status_code, bytes(entry.reply)))

    def _replayed_again(self, again: ReplayAgain) -> None:
        """ProgramCalls._replay_again: the program starts again (the rejoin came with it)."""
        entry = again.entry
        self._say(replay_again(self.id, again, 0)[0])
        # What it answered before the give-up came from the log and must match; from
        # the give-up on it ran on its own answer.
        self.accepted_upto = max(self.accepted_upto, entry.reqnr - 1)

    def _answered(self, turn: Turn, entry: ring_pb2.LogEntry | None, code: int = 0) -> None:
        """The program gets its answer (``entry``, or the ``code`` it gave up with) and goes
        on to its next call; a settling turn just ends."""
        if self.turn is turn:
            self.turn = None
        if turn.call is None:
            return
        if entry is None:
            self.view.append((code, b""))
        else:
            self.view.append((entry.status_code, bytes(entry.reply)))
        self.pc += 1
        if self.pc == len(self.program):
            self.done_at = self.world.loop.now
            self._apply(self.protocol.on_mission_done())  # ProgramCalls.mission_done
            self.world.program_done(self)
        else:
            self._schedule_call()

    def _stop(self) -> None:
        """The call raised the mission's failure: the program ends (failed)."""
        turn, self.turn = self.turn, None
        if turn is not None and turn.call is not None:
            self.program_failed = True
            self._apply(self.protocol.on_mission_done())

    # -- the program gives up on a call (a deadline, a cancellation) --------------

    def give_up(self, code: grpc.StatusCode) -> bool:
        """The program's call is cancelled (``ProgramCalls.call``'s CancelledError): an
        Invoke on its way is cancelled at the drone, and the core told (``CallFlow.gave_up``:
        logged as the call's outcome if it is still ours to log, else queued as abandoned,
        settled from the log by the next call). False if nothing was cancelled."""
        turn = self.turn
        if turn is None or turn.call is None or not self.alive:
            return False
        link = self.drone_link
        if turn.call_id and turn.connection == link.generation and link.usable():
            link.to_drone(0, self.world.drone.receive_cancel, turn.call_id)
        self.turn = None  # what was under way for it is let go
        effects, reqnr = turn.flow.gave_up(code), turn.flow.reqnr
        if any(isinstance(e, Seen) and e.entry.given_up for e in effects):
            self.world.given_up[reqnr] = code
        self._apply(effects)
        if reqnr:
            self.world.trace(f"controller {self.id} gives up on request {reqnr} ({code.name})")
        else:
            call = turn.call.index
            self.world.trace(f"controller {self.id} gives up on call {call} while waiting")
        self._answered(turn, None, code.value[0])
        return True

    # -- for the fault injector and the oracles -----------------------------------

    @property
    def done(self) -> bool:
        """The program answered every call."""
        return self.pc == len(self.program)

    @property
    def master_like(self) -> bool:
        """Master in any sense: issue 10 (failover) is what killing one needs."""
        p = self.protocol
        if p.master or p.state is State.ACTIVE or self.world.drone.seq.master == self.id:
            return True
        if any(message.handover for message in p.log_queue.values()):
            return True  # made master by a message it has not handled yet
        # Its own messages or a handover message not yet taken by their receiver.
        return any(
            message.origin == self.id or message.handover
            for link in self.links.values()
            for message in link.unacked.values()
        )

    def holding(self) -> dict[str, str]:
        """ControllerNode.stall_conditions (``status.holding``): what it waits for now."""
        session, turn = self.session, self.turn
        link = self.ring.get(self.protocol.successor)
        in_flight = None
        if turn is not None and isinstance(turn.io, Invoke):
            in_flight = (turn.io.sent.reqnr, turn.io.sent.method)
        sight = Sight(
            drone=None if session is None else ("the drone", session.connected),
            standby_address="the drone",
            standby_up=self.drone_link.usable(),
            in_flight=in_flight,
            successor_link=None if link is None else (link.up, len(link.unacked)),
        )
        return holding(self.protocol, self.routed_around, sight)

    @property
    def waits_for(self) -> str:
        """What the program's call waits for now ("" : no call), for the explorer's states."""
        turn = self.turn
        return "" if turn is None else type(turn.io).__name__

    @property
    def answering(self) -> int:
        """The request number the program's call is being answered with (0: none)."""
        turn = self.turn
        return 0 if turn is None or turn.call is None else turn.flow.reqnr

    def waiting_call_reqnr(self) -> int | None:
        """The reqnr of the call held while PASSIVE, if the program is held."""
        turn = self.turn
        if turn is not None and turn.call is not None and isinstance(turn.io, WaitForChange):
            return turn.call.reqnr if not turn.flow.reqnr else None
        return None
