"""The mission program's calls on a controller node, one at a time.

A driver of ``ControllerCore``'s call events (``settle``, ``answer``, ``logged``,
``gave_up``) and of ``invoking``'s rules for a drone call's outcome: a call loops
over the core's step, waits on the node's change event where the core holds it,
asks the Clock or the drone where the core says so, and carries out the effects
through the node (``ControllerNode.apply``). It keeps what the program saw: the
reply chain, the mission's state and the failure that stopped it.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import time
from collections.abc import Callable, Generator, Sequence
from typing import TYPE_CHECKING, TypeVar

import grpc

from baton.controller.call_flow import (
    Apply,
    CallFlow,
    Invoke,
    Invoked,
    Io,
    LookAtSession,
    Pause,
    ReadClock,
    RetriesEnded,
    SessionSeen,
    WaitConnected,
    WaitForChange,
)
from baton.controller.core import CLOCK_NOW, CLOCK_SERVICE, CoreEffect, ReplayAgain
from baton.controller.drone_link import DroneSession, Retry, refusal_of
from baton.controller.notes import replay_again
from baton.rpc.errors import StatusError
from baton.stalls import Wait
from baton.v1 import drone_api_pb2 as api
from baton.v1 import ring_pb2

if TYPE_CHECKING:
    from baton.controller.node import ControllerNode

# A call that comes while the previous one is pending waits this long for it to end
# before it is refused as concurrent: a program that gave up on a call (its deadline,
# a cancelled stream) makes its next one at once, and that one can reach the
# controller first (on another stream or connection, in no fixed order).
BUSY_GRACE_S = 2.0
# What a flow yields while a drone request is being re-sent (``ProgramCalls.drone_wait``).
_RETRYING = (Pause, LookAtSession, WaitConnected, Invoke)
_T = TypeVar("_T")


class ProgramCalls:
    """The local mission program's drone-API calls for one ``ControllerNode``."""

    def __init__(self, node: ControllerNode) -> None:
        self.node = node
        self.busy: str | None = None  # the method of the call pending, if any
        self.idle = asyncio.Event()  # set while no call is pending
        self.idle.set()
        self.mission: ring_pb2.MissionState.ValueType = ring_pb2.MISSION_STATE_NONE
        self.mission_error = ""
        self.failure: StatusError | None = None
        # A request the drone could not take, being re-sent (``_invoke_drone``).
        self.drone_wait: Wait | None = None
        self.in_flight: tuple[int, str] | None = None  # the request the drone has now
        self._reply_chain = hashlib.sha256()
        self.drone_calls = 0  # calls answered so far that went to the drone (not the Clock)
        # Times the program was restarted to replay a call it gave up on (``_replay_again``).
        self.restarts = 0
        # Bumped when the controller rejoins after being fenced: calls of the
        # mission program from before then are refused, not answered.
        self.incarnation = 0
        self._settler: asyncio.Task[None] | None = None  # for those left when the program ended
        self._retry_log = Retry(0.0)  # when a request's re-sending is logged (stalls.py)

    @property
    def reply_chain(self) -> bytes:
        """SHA-256 chain over every reply the mission program has seen, in order."""
        return self._reply_chain.digest()

    def reset(self) -> None:
        """The controller rejoins with nothing: the calls of the program before are
        refused (``incarnation``), and what it saw is forgotten."""
        self.incarnation += 1
        self.stop()
        self.mission, self.mission_error = ring_pb2.MISSION_STATE_NONE, ""
        self.failure = None
        self.drone_wait, self.in_flight, self.busy = None, None, None
        self.idle.set()
        self._reply_chain = hashlib.sha256()
        self.drone_calls = 0

    def stop(self) -> None:
        """Stops settling the calls left when the program ended."""
        if self._settler is not None:
            self._settler.cancel()
            self._settler = None

    def fail(self, error: StatusError) -> None:
        """The mission stops on this controller (``Fail``): every call ends with ``error``."""
        self.failure = error
        self.mission = ring_pb2.MISSION_STATE_FAILED
        self.mission_error = error.message
        self.node.log.error("mission stopped", error=error.message)

    def seen(self, entry: ring_pb2.LogEntry) -> None:
        """Counts the entry the protocol consumed (``Seen``) into the reply chain."""
        if not entry.method.startswith(CLOCK_SERVICE):
            self.drone_calls += 1
        self._reply_chain.update(
            entry.reqnr.to_bytes(8, "big")
            + entry.status_code.to_bytes(4, "big", signed=True)
            + hashlib.sha256(entry.reply).digest()
        )

    async def mission_done(self, failed: bool, error: str) -> bool:
        """The local mission program ended; the master flushes its last entries."""
        node = self.node
        self.mission = ring_pb2.MISSION_STATE_FAILED if failed else ring_pb2.MISSION_STATE_DONE
        if error:
            self.mission_error = self.mission_error or error
        effects = node.protocol.on_mission_done()
        await node.apply(effects)
        node.log.info("mission program ended", failed=failed, flushed=bool(effects))
        if node.core.abandoned and self._settler is None:
            # Its last call was given up while this replica waited: no next
            # call will settle it, so the entry is consumed here when it comes,
            # else it would hold REPLAY for ever.
            self._settler = asyncio.create_task(self._settle_after_the_end())
        return bool(effects)

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
        if self.busy is not None:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(BUSY_GRACE_S):
                    await self.idle.wait()
        if self.busy is not None:
            raise StatusError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"controller {self.node.id}: concurrent call {method} while {self.busy} is "
                "pending; a mission program makes one drone call at a time",
            )
        self.busy = method
        self.idle.clear()
        incarnation = self.incarnation
        try:
            if self.mission == ring_pb2.MISSION_STATE_NONE:
                self.mission = ring_pb2.MISSION_STATE_RUNNING
            flow = CallFlow(self.node.core, method, request, self.node.config.drone_retry_limit)
            try:
                return await self._drive(flow.run(), incarnation)
            except asyncio.CancelledError:
                given_up = flow.gave_up(gave_up()) if incarnation == self.incarnation else []
                if given_up:
                    await asyncio.shield(self._apply(given_up))
                raise
        finally:
            if incarnation == self.incarnation:
                self.busy, self.drone_wait = None, None
                self.idle.set()

    async def _settle_after_the_end(self) -> None:
        flow = CallFlow(self.node.core, "", b"", self.node.config.drone_retry_limit)
        try:
            await self._drive(flow.settle(), self.incarnation)
        except StatusError:
            pass  # the mission's failure, already recorded by fail

    def _check_incarnation(self, incarnation: int) -> None:
        """ABORTED for a call of the mission program from before a rejoin."""
        if incarnation != self.incarnation:
            raise StatusError(
                grpc.StatusCode.ABORTED,
                f"controller {self.node.id} rejoined as a replica after a takeover: its "
                "mission program is restarted, and this call of the one before is not answered",
            )

    async def _drive(self, flow: Generator[Io, object, _T], incarnation: int) -> _T:
        """Runs ``flow`` (``call_flow.CallFlow``): carries out what it yields and sends it
        the result, until it returns. The call ends with the mission's failure, or ABORTED
        once the controller rejoined (a call of the program from before)."""
        result: object = None
        io: Io | None = None
        changed = self.node.changed
        while True:
            self._check_incarnation(incarnation)
            if self.failure is not None:
                raise self.failure
            if not isinstance(io, Apply):
                # A wait is for a change since the core was last asked: one made while
                # what it asked for was applied counts (it may be another task's).
                changed = self.node.changed
            try:
                io = flow.send(result)
            except StopIteration as stop:
                return stop.value  # type: ignore[no-any-return]
            result = await self._perform(io, changed)

    async def _perform(self, io: Io, changed: asyncio.Event) -> object:
        """What one turn of a call's flow asks for, done; ``changed``: the node's change
        event as it was when the core was last asked."""
        node = self.node
        if not isinstance(io, _RETRYING):
            self.drone_wait = None  # the request's re-sending is over
        if isinstance(io, Apply):
            await self._apply(io.effects)
        elif isinstance(io, WaitForChange):
            await changed.wait()
        elif isinstance(io, ReadClock):
            return await self._clock_call(io.method, io.request)
        elif isinstance(io, LookAtSession):
            drone = node.drone
            connected = drone is not None and drone.connected.is_set()
            epoch = drone.epoch if drone is not None and connected else 0
            return SessionSeen(drone is not None, connected, epoch, time.monotonic())
        elif isinstance(io, WaitConnected):
            assert node.drone is not None
            await self._wait_connected(node.drone)
        elif isinstance(io, Invoke):
            return await self._invoke(io)
        elif isinstance(io, Pause):
            self.drone_wait = Wait(
                "retry",
                f"request {io.reqnr} ({io.method}): drone unavailable ({io.details})",
                io.waited,
            )
            if io.attempts == 0:
                self._retry_log = Retry(node.config.drone_retry_limit)
            if self._retry_log.should_log():
                node.log.warning(
                    "drone unavailable; re-sending",
                    reqnr=io.reqnr,
                    waited_s=round(io.waited, 1),
                    limit_s=node.config.drone_retry_limit,
                    detail=io.details,
                )
            await asyncio.sleep(io.seconds)
        elif isinstance(io, RetriesEnded):
            node.log.warning(
                "drone still unavailable; the call fails",
                reqnr=io.reqnr,
                waited_s=round(io.waited, 1),
            )
        return None

    async def _invoke(self, io: Invoke) -> Invoked:
        """The request to the drone, and what came of it."""
        node, sent = self.node, io.sent
        drone = node.drone
        assert drone is not None
        self.in_flight = (sent.reqnr, sent.method)
        try:
            reply = await drone.invoke(
                sent.reqnr,
                sent.method,
                sent.request,
                timeout_s=io.timeout_s,
                carried=node.core.carried(node.preparation_progress()),
            )
        except grpc.aio.AioRpcError as exc:
            return Invoked(time.monotonic(), None, exc.code(), exc.details() or "", refusal_of(exc))
        finally:
            self.in_flight = None
        return Invoked(time.monotonic(), (reply.payload, reply.epoch, reply.signature))

    async def _apply(self, effects: Sequence[CoreEffect]) -> None:
        """``ControllerNode.apply`` for the call path: a mission stopped (``Fail``) or a
        program that starts again (``ReplayAgain``) ends the call with its status.
        Nothing to apply wakes nobody: a call that waits must not wake itself."""
        if effects:
            await self.node.apply(effects)
        again = next((e for e in effects if isinstance(e, ReplayAgain)), None)
        if again is not None:
            self._replay_again(again)
        if self.failure is not None:
            raise self.failure

    def _replay_again(self, again: ReplayAgain) -> None:
        """The program starts again from the log, its call ABORTED (``notes.replay_again``)."""
        self.restarts += 1
        note, aborted = replay_again(self.node.id, again, self.restarts)
        getattr(self.node.log, note.level)(note.text, **note.fields)
        raise StatusError(grpc.StatusCode.ABORTED, aborted)

    async def _clock_call(self, method: str, request: bytes) -> bytes:
        """Clock calls are answered here and logged like drone replies.

        Logging Sleep too means a new master replays the sleeps its
        predecessor already slept instead of sleeping them again; a sleep cut
        short by a handover is discarded like any reply in flight. They also
        go to the drone with the next drone call (``ControllerCore.answered_here``),
        which keeps them for a taker: after a takeover the lost master's
        Sleeps are not slept again and its times are read again the same
        (docs/design.md, "Takeover").
        """
        clock = self.node.clock
        if method == CLOCK_NOW:
            return api.NowReply(unix_time_s=clock.now()).SerializeToString()
        await clock.sleep(api.SleepRequest.FromString(request).seconds)
        return api.SleepReply().SerializeToString()

    async def _wait_connected(self, drone: DroneSession) -> None:
        waiters = {
            asyncio.create_task(drone.connected.wait()),
            asyncio.create_task(self.node.changed.wait()),
        }
        try:
            await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for waiter in waiters:
                waiter.cancel()
