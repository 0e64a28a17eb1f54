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
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import grpc

from baton.controller.core import (
    CLOCK_NOW,
    CLOCK_SERVICE,
    Answer,
    AskClock,
    CoreEffect,
    Hold,
    ReplayAgain,
)
from baton.controller.drone_link import DroneSession, Retry, refusal_of
from baton.controller.invoking import Sent, failed, replied
from baton.controller.notes import replay_again
from baton.controller.protocol import State
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

    async def _settle_after_the_end(self) -> None:
        try:
            await self._settle_abandoned()
        except StatusError:
            pass  # the mission's failure, already recorded by fail

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
            try:
                await self._settle_abandoned()
            except asyncio.CancelledError:
                if incarnation == self.incarnation:
                    self.node.core.gave_up(0, method, request, gave_up())
                raise
            return await self._answer(method, request, gave_up, incarnation)
        finally:
            if incarnation == self.incarnation:
                self.busy = None
                self.idle.set()

    async def _settle_abandoned(self) -> None:
        """Gives the log's entry to each call the program gave up on while this controller
        waited (``ControllerCore.settle``), waiting for the log or the drone's word."""
        while True:
            if self.failure is not None:
                raise self.failure
            changed = self.node.changed
            done, effects = self.node.core.settle()
            await self._apply(effects)
            if done:
                return
            await changed.wait()

    def _check_incarnation(self, incarnation: int) -> None:
        """ABORTED for a call of the mission program from before a rejoin."""
        if incarnation != self.incarnation:
            raise StatusError(
                grpc.StatusCode.ABORTED,
                f"controller {self.node.id} rejoined as a replica after a takeover: its "
                "mission program is restarted, and this call of the one before is not answered",
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
        node = self.node
        while True:
            self._check_incarnation(incarnation)
            if self.failure is not None:
                raise self.failure
            changed = node.changed
            step, effects = node.core.answer(method, request)
            await self._apply(effects)
            try:
                if isinstance(step, Answer):
                    return step.entry
                if isinstance(step, Hold):
                    await changed.wait()
                    continue
                if isinstance(step, AskClock):
                    reply = await self._clock_call(method, request)
                    entry: ring_pb2.LogEntry | None = step.entry(method, request, reply)
                else:
                    entry = await self._invoke_drone(step.reqnr, method, request, step.digest)
            except asyncio.CancelledError:
                if incarnation == self.incarnation:
                    reqnr = 0 if isinstance(step, Answer) else step.reqnr
                    given_up = node.core.gave_up(reqnr, method, request, gave_up())
                    await asyncio.shield(self._apply(given_up))
                raise
            if entry is None:
                continue  # the state changed: asked again
            logged, effects = node.core.logged(step.reqnr, entry)
            await self._apply(effects)
            if logged is not None:
                return logged

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

    async def _invoke_drone(
        self, reqnr: int, method: str, request: bytes, digest: bytes
    ) -> ring_pb2.LogEntry | None:
        try:
            return await self._invoke_drone_retrying(reqnr, method, request, digest)
        finally:
            self.drone_wait = None
            self.in_flight = None

    async def _invoke_drone_retrying(
        self, reqnr: int, method: str, request: bytes, digest: bytes
    ) -> ring_pb2.LogEntry | None:
        """Sends the request until it has an outcome (``invoking.failed``'s rules)."""
        node = self.node
        retry = Retry(node.config.drone_retry_limit)
        while True:
            drone = node.drone
            if drone is None or node.protocol.state is not State.ACTIVE:
                return None
            if not drone.connected.is_set():
                await self._wait_connected(drone)
                continue
            sent = Sent(reqnr, method, request, digest, drone.epoch)
            try:
                self.in_flight = (reqnr, method)
                reply = await drone.invoke(
                    reqnr,
                    method,
                    request,
                    timeout_s=max(1.0, retry.limit_s - retry.waited()),
                    carried=node.core.carried(node.preparation_progress()),
                )
                return replied(sent, reply.payload, reply.epoch, reply.signature)
            except grpc.aio.AioRpcError as exc:
                detail, waited = exc.details() or "", retry.waited()
                outcome = failed(
                    node.core,
                    sent,
                    exc.code(),
                    detail,
                    refusal_of(exc),
                    waited,
                    retry.limit_s,
                    retry.attempts,
                )
            if outcome.pause is not None:
                self.drone_wait = Wait(
                    "retry", f"request {reqnr} ({method}): drone unavailable ({detail})", waited
                )
                if retry.should_log():
                    node.log.warning(
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
                await node.apply(outcome.effects)
            elif retry.attempts:
                node.log.warning(
                    "drone still unavailable; the call fails",
                    reqnr=reqnr,
                    waited_s=round(waited, 1),
                )
            return outcome.entry

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
