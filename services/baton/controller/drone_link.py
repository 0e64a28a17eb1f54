"""The master's connection to the drone: the Connect stream and its calls.

Opened when the controller becomes ACTIVE and closed when it stops being
ACTIVE (docs/design.md, protocol note 5), and once at start to ask the
drone who the master is; the time from opening to the drone's first event is
T_conn. A session's channel is one kept connected in advance when it is
ready (``WarmChannel``), so that a handover's connection is the Connect call
alone. The Connected event carries the epoch of the mastership, which every
Invoke of the session carries; a handover notice on the stream, or a Connect
refused because another controller is master, reach the controller through
``DroneEvents``. The session's drone calls travel on one kept InvokeStream
(``InvokeCalls``; docs/design.md, "The proxy path").
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import grpc

from baton.controller.core import DroneRefusal
from baton.logs import BoundLogger
from baton.rpc.channels import aio_channel
from baton.rpc.outcomes import error_of
from baton.rpc.streams import write_message
from baton.rpc.tls import DRONE, Identity, Tls
from baton.stalls import StallWatch
from baton.tasks import TaskSet
from baton.v1 import drone_pb2, drone_pb2_grpc

# Longest a call in flight at close may take to finish (a large picture on a slow link).
CLOSE_GRACE_S = 60.0
# The same when the controller stops: its process has STOP_DEADLINE_S in all.
STOP_GRACE_S = 1.0
# How long a prepared handover's word between requests may take to be heard.
REPORT_TIMEOUT_S = 2.0
# How long an answer to the drone's ping may take (a later one replaces it), and
# how many may be in flight at once (more pings wait for none: not answered).
PING_ANSWER_TIMEOUT_S = 10.0
PING_ANSWERS_IN_FLIGHT = 4


def refusal_of(error: grpc.aio.AioRpcError) -> DroneRefusal | None:
    """The drone's master, epoch and last reqnr from a FAILED_PRECONDITION that names them."""
    return DroneRefusal.of_status(error.code(), dict(error.trailing_metadata() or ()))


@dataclass
class Retry:
    """A drone call re-sent with back-off (``invoking.failed``: when, and for how long),
    for at most ``limit_s`` of wall time; its wait is logged at once and again every
    5 s (stalls.py)."""

    limit_s: float
    started: float = field(default_factory=time.monotonic)
    attempts: int = 0  # the pauses so far
    _log_watch: StallWatch = field(default_factory=lambda: StallWatch(threshold_s=0.0))

    def waited(self) -> float:
        """Seconds since the first try."""
        return time.monotonic() - self.started

    def should_log(self) -> bool:
        """True on the first retry and then every 5 s (StallWatch's rhythm)."""
        now = time.monotonic()
        waits = self._log_watch.update(now, {"retry": "drone unavailable"})
        return self._log_watch.due_for_log(now, waits)


class DroneEvents(Protocol):
    """What a session tells its controller."""

    def granted(self, connected: drone_pb2.Connected) -> None:
        """Connected: the drone holds this controller as master in ``connected.epoch``
        (by takeover or not), and its watermark; the replies it retains above what the
        controller holds follow, up to ``connected.retained_through``."""

    def retained(self, replies: Sequence[drone_pb2.RetainedReply]) -> None:
        """A batch of those replies, in order."""

    def notice(self, notice: drone_pb2.HandoverNotice) -> None:
        """A handover notice on the stream (the stream then ends)."""

    def prepare(self, prepare: drone_pb2.PrepareHandover) -> None:
        """A planned handover: catch the target up (docs/design.md, "Prepared handover")."""

    def refused(self, refusal: DroneRefusal) -> None:
        """Connect refused: another controller is master, and no notice is owed to this one."""

    def down(self) -> None:
        """The Connect stream broke (it is connected again after a back-off)."""


_InvokeStream = grpc.aio.StreamStreamCall[drone_pb2.InvokeCall, drone_pb2.InvokeOutcome]


def _failure(code: grpc.StatusCode, details: str) -> grpc.aio.AioRpcError:
    """A drone call's failure as its unary Invoke raises it, without metadata."""
    return grpc.aio.AioRpcError(code, grpc.aio.Metadata(), grpc.aio.Metadata(), details)


class InvokeCalls:
    """Drone calls as messages on one kept InvokeStream (drone.proto), each
    raising what its unary Invoke would: its reply, or grpc.aio.AioRpcError.

    The stream opens at the first call and again at the first call after it
    ended. A call's failure comes as its outcome, with Invoke's code and
    trailing metadata (``rpc.outcomes.error_of``). A call the stream ended
    under fails as Invoke fails when the connection drops: UNAVAILABLE (or the
    stream's own status, e.g. RESOURCE_EXHAUSTED for a request over the size
    limit), and the drone keeps what it did for the same request sent again.
    A call waits for the drone to be reachable (``wait_for_ready``) for at most
    its timeout, then fails DEADLINE_EXCEEDED; its write cut short by the
    timeout cancels the stream, which its next call opens again.
    """

    def __init__(self, stub: drone_pb2_grpc.DroneAsyncStub, log: BoundLogger) -> None:
        self._stub = stub
        self._log = log
        # The stream now, None until the first call and after it ended.
        self._stream: _InvokeStream | None = None
        self._reader: asyncio.Task[None] | None = None
        self._waiting: dict[int, asyncio.Future[drone_pb2.InvokeOutcome]] = {}
        self._numbers = itertools.count(1)
        self._writing = asyncio.Lock()

    async def invoke(
        self, request: drone_pb2.InvokeRequest, timeout_s: float | None
    ) -> drone_pb2.InvokeReply:
        number = next(self._numbers)
        waiter: asyncio.Future[drone_pb2.InvokeOutcome] = asyncio.get_running_loop().create_future()
        self._waiting[number] = waiter
        try:
            async with asyncio.timeout(timeout_s):
                async with self._writing:
                    await self._write(drone_pb2.InvokeCall(call=number, request=request))
                outcome = await waiter
        except TimeoutError:
            raise _failure(
                grpc.StatusCode.DEADLINE_EXCEEDED,
                f"no outcome for request {request.reqnr} in {timeout_s:g} s",
            ) from None
        finally:
            self._waiting.pop(number, None)
        if outcome.HasField("failure"):
            raise error_of(outcome.failure)
        return outcome.reply

    async def _write(self, call: drone_pb2.InvokeCall) -> None:
        """Writes ``call`` on the stream. One that finished before its reader took it away
        fails the call as ``_read`` fails the calls it ends (UNAVAILABLE for a stream
        cancelled or ended, else its own status)."""
        try:
            await write_message(self._open(), call)
        except grpc.aio.AioRpcError as exc:
            # The reader takes the stream away, failing the calls it carried; until it has,
            # a call fails here too (its caller sends it again after a pause).
            if exc.code() is not grpc.StatusCode.CANCELLED:
                raise
            raise _failure(
                grpc.StatusCode.UNAVAILABLE,
                f"the invoke stream ended: {exc.code().name}: {exc.details()}",
            ) from None

    def _open(self) -> _InvokeStream:
        if self._stream is None:
            self._stream = self._stub.InvokeStream(wait_for_ready=True)
            self._reader = asyncio.create_task(self._read(self._stream), name="invoke-outcomes")
        return self._stream

    async def _read(self, stream: _InvokeStream) -> None:
        code, details = grpc.StatusCode.UNAVAILABLE, "the drone ended the invoke stream"
        try:
            async for outcome in stream:
                waiter = self._waiting.get(outcome.call)
                if waiter is not None and not waiter.done():
                    waiter.set_result(outcome)
        except grpc.aio.AioRpcError as exc:
            if exc.code() is not grpc.StatusCode.CANCELLED:
                code = exc.code()
            details = f"the invoke stream ended: {exc.code().name}: {exc.details()}"
        finally:
            if self._stream is stream:
                self._stream = None
            error = _failure(code, details)
            for waiter in self._waiting.values():
                if not waiter.done():
                    waiter.set_exception(error)
        self._log.info("invoke stream ended", code=code.name, detail=details)

    async def close(self, grace: float) -> None:
        """Ends the stream once the calls in flight have their outcomes (for at most
        ``grace`` seconds)."""
        if self._waiting:
            await asyncio.wait(list(self._waiting.values()), timeout=grace)
        if self._stream is not None:
            self._stream.cancel()
        if self._reader is not None:
            with contextlib.suppress(asyncio.CancelledError):
                await self._reader


class WarmChannel:
    """A channel to the drone kept connected for the controller's next session.

    A session started while it is READY takes it: its TCP connection (and its
    TLS handshake) were made long before, and the handover's connection is the
    Connect call alone (docs/design.md, "A warm channel for the next
    mastership"). A new one then starts connecting for the session after. One
    not READY (the link was cut and it waits to reconnect, or it has not
    connected yet) is closed, and the session gets a fresh channel, as it
    would without this one: never slower than connecting then.
    """

    def __init__(self, address: str, tls: Tls | None = None, drone: Identity = DRONE) -> None:
        self.address = address
        self._tls = tls
        self._drone = drone  # the identity the drone's certificate must name
        self._spare: grpc.aio.Channel | None = None
        self._closing = TaskSet()
        self.warm = 0  # sessions given a channel connected in advance
        self.cold = 0  # and a fresh one

    def _connecting(self) -> grpc.aio.Channel:
        channel = aio_channel(self.address, self._tls, self._drone, keep_idle=True)
        channel.get_state(try_to_connect=True)
        return channel

    def start(self) -> None:
        """Starts connecting the first spare."""
        if self._spare is None:
            self._spare = self._connecting()

    def take(self) -> tuple[grpc.aio.Channel, bool]:
        """A channel for a session, and whether it was connected already; the session
        owns it (closes it). A new spare starts connecting."""
        spare, self._spare = self._spare, self._connecting()
        if spare is not None and spare.get_state() is grpc.ChannelConnectivity.READY:
            self.warm += 1
            return spare, True
        if spare is not None:
            self._closing.spawn(spare.close(), name="drone-spare-close")
        self.cold += 1
        return aio_channel(self.address, self._tls, self._drone), False

    async def close(self) -> None:
        """Closes the spare."""
        spare, self._spare = self._spare, None
        if spare is not None:
            await spare.close()
        await self._closing.drain()


class DroneSession:
    """One ACTIVE period's connection to the drone service."""

    def __init__(
        self,
        controller_id: int,
        address: str,
        channel: grpc.aio.Channel,
        events: DroneEvents,
        log: BoundLogger,
        connect_request: Callable[[], drone_pb2.ConnectRequest] | None = None,
    ) -> None:
        """``channel``: the session's own to ``address`` (it closes it), connected in
        advance or not (``WarmChannel.take``)."""
        self.controller_id = controller_id
        # The Connect, read at every (re)connect (``ControllerCore.connect_request``).
        self._connect_request = connect_request or (
            lambda: drone_pb2.ConnectRequest(controller_id=controller_id)
        )
        self.address = address
        self._events_to = events
        self._log = log
        self.epoch = 0  # from the Connected event
        self._channel = channel
        self._stub = drone_pb2_grpc.DroneStub(self._channel)
        self._calls = InvokeCalls(self._stub, log)
        self.connected = asyncio.Event()
        self.t_conn_s: float | None = None
        # When each Connected event came (Unix seconds, wall clock): the status's
        # drone_connected_at.
        self.connected_at: list[float] = []
        self.opened_at = time.monotonic()
        self._events: asyncio.Task[None] | None = None
        # The operator's pause as the drone last said it (DroneEvent.operator): why a
        # request waits at the drone; "" when not paused.
        self.operator_pause = ""

    def open(self) -> None:
        """Starts connecting; ``connected`` is set when the drone's first event arrives."""
        self._events = asyncio.create_task(self._follow_events(), name="drone-events")

    async def _follow_events(self) -> None:
        backoff = 0.05
        while True:
            try:
                call = self._stub.Connect(self._connect_request(), wait_for_ready=True)
                async for event in call:
                    if event.HasField("connected"):
                        if self.t_conn_s is None:
                            self.t_conn_s = time.monotonic() - self.opened_at
                        self.epoch = event.connected.epoch
                        self.connected_at.append(time.time())
                        self.connected.set()
                        self._log.info(
                            "drone connected",
                            t_conn_ms=round((self.t_conn_s or 0) * 1000, 3),
                            drone_last_reqnr=event.connected.last_reqnr,
                            epoch=self.epoch,
                            retained_through=event.connected.retained_through,
                            takeover=event.connected.takeover,
                        )
                        self._events_to.granted(event.connected)
                    elif event.HasField("retained"):
                        self._events_to.retained(event.retained.replies)
                    elif event.HasField("prepare"):
                        self._events_to.prepare(event.prepare)
                    elif event.HasField("operator"):
                        self.operator_pause = event.operator.paused
                    elif event.HasField("handover"):
                        self._events_to.notice(event.handover)
                        return
                raise ConnectionError("drone ended the Connect stream without a handover notice")
            except asyncio.CancelledError:
                raise
            except grpc.aio.AioRpcError as exc:
                refusal = refusal_of(exc)
                if refusal is not None:
                    self._events_to.refused(refusal)
                    return
                self._log.warning(
                    "drone stream down; reconnecting", code=exc.code().name, detail=exc.details()
                )
            except ConnectionError as exc:
                self._log.warning("drone stream down; reconnecting", error=str(exc))
            self.connected.clear()
            self._events_to.down()
            await asyncio.sleep(backoff)
            backoff = min(backoff * 2, 1.0)

    async def invoke(
        self,
        reqnr: int,
        method: str,
        payload: bytes,
        timeout_s: float | None = None,
        carried: drone_pb2.InvokeRequest | None = None,
    ) -> drone_pb2.InvokeReply:
        """Sends request ``reqnr`` in this session's epoch, with what it ``carried``
        (``ControllerCore.carried``); raises grpc.aio.AioRpcError.

        It waits for the drone to be reachable (``wait_for_ready``) for at
        most ``timeout_s``, then fails DEADLINE_EXCEEDED.
        """
        request = drone_pb2.InvokeRequest(
            controller_id=self.controller_id,
            reqnr=reqnr,
            method=method,
            payload=payload,
            epoch=self.epoch,
        )
        if carried is not None:
            request.MergeFrom(carried)
        return await self._calls.invoke(request, timeout_s)

    async def report_preparation(self, progress: drone_pb2.PreparationProgress) -> bool:
        """Tells the drone between requests how far a prepared handover's target is
        behind; whether it moved the master on it. Raises grpc.aio.AioRpcError."""
        reply: drone_pb2.PreparationReportReply = await self._stub.ReportPreparation(
            drone_pb2.PreparationReport(
                controller_id=self.controller_id, epoch=self.epoch, progress=progress
            ),
            timeout=REPORT_TIMEOUT_S,
        )
        return reply.moved

    async def close(self, grace: float = CLOSE_GRACE_S) -> None:
        """Closes the stream, then the channel once calls in flight have their replies
        (for at most ``grace`` seconds).

        A call in flight at a handover (footnote 2) must complete normally: its
        reply is then discarded by the controller, not torn down mid-call. A
        controller stopping waits less (``STOP_GRACE_S``).
        """
        if self._events is not None:
            self._events.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._events
        started = time.monotonic()
        await self._calls.close(grace)
        await self._channel.close(grace=max(0.0, grace - (time.monotonic() - started)))


class DroneStandby:
    """The standby stream a controller holds to the drone for as long as it runs.

    It is how the drone knows the controller is reachable, and where a
    TakeOver comes (``on_take_over``). The drone pings on it about once a
    second, and the controller answers on the same channel (``AnswerPing``):
    the drone measures the link's round trip (docs/design.md, "Link health").
    Re-opened with back-off when it breaks; ``up`` says whether it is open now.
    """

    def __init__(
        self,
        controller_id: int,
        address: str,
        on_take_over: Callable[[drone_pb2.TakeOver], Awaitable[None]],
        log: BoundLogger,
        tls: Tls | None = None,
        drone: Identity = DRONE,
        on_down: Callable[[], None] = lambda: None,
    ) -> None:
        self.controller_id = controller_id
        self.address = address
        self._tls = tls
        self._drone = drone  # the identity the drone's certificate must name
        self._on_take_over = on_take_over
        self._on_down = on_down  # called when the stream, once up, broke
        self._log = log
        self.up = False
        self._task: asyncio.Task[None] | None = None
        self._answers = TaskSet()
        self.pings_answered = 0

    def start(self) -> None:
        """Starts holding the stream."""
        if self._task is None:
            self._task = asyncio.create_task(self._hold(), name="drone-standby")

    async def _hold(self) -> None:
        backoff = 0.05
        async with aio_channel(self.address, self._tls, self._drone) as channel:
            stub = drone_pb2_grpc.DroneStub(channel)
            while True:
                try:
                    call = stub.Standby(
                        drone_pb2.StandbyRequest(controller_id=self.controller_id),
                        wait_for_ready=True,
                    )
                    async for event in call:
                        if event.HasField("held"):
                            self.up, backoff = True, 0.05
                        elif event.HasField("take_over"):
                            await self._on_take_over(event.take_over)
                        elif event.HasField("ping"):
                            self._answer(stub, event.ping.seq)
                except asyncio.CancelledError:
                    raise
                except grpc.aio.AioRpcError as exc:
                    if self.up:
                        self._log.warning(
                            "standby stream to the drone down; reconnecting",
                            code=exc.code().name,
                            detail=exc.details(),
                        )
                was_up, self.up = self.up, False
                if was_up:
                    self._on_down()
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2, 1.0)

    def _answer(self, stub: drone_pb2_grpc.DroneAsyncStub, seq: int) -> None:
        """Answers the drone's ping ``seq`` in the background (the stream reads on)."""
        if len(self._answers) >= PING_ANSWERS_IN_FLIGHT:
            return  # the link is that slow: the drone measures it by the ones in flight

        async def answer() -> None:
            try:
                await stub.AnswerPing(
                    drone_pb2.PingAnswer(controller_id=self.controller_id, seq=seq),
                    timeout=PING_ANSWER_TIMEOUT_S,
                )
                self.pings_answered += 1
            except grpc.aio.AioRpcError as exc:
                self._log.debug("ping answer failed", seq=seq, code=exc.code().name)
            except grpc.aio.UsageError:
                pass  # the channel closed: the stream is being re-opened or we stop

        self._answers.spawn(answer(), name="ping-answer")

    async def stop(self) -> None:
        """Stops holding it."""
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        self.up = False
