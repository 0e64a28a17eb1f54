"""Replays a saved mission log against a mission program, offline (``baton replay``).

The controller's own REPLAY does the work: a ``ControllerProtocol`` is fed the
log file's messages as the ring feeds a replica (``on_log``), and answers the
program's calls from them with ``replay``, which checks each request's digest
and raises ``NonDeterminismError`` at the first one the log does not hold. So
an offline replay passes exactly when a replica's program would have replayed
that log in the ring.

The program runs in this process, with a ``Drone`` whose channel answers from
the protocol (``ReplayChannel``; an ``async def`` mission gets the asyncio
``Drone`` over ``AioReplayChannel``, the same answers awaited): the SDK
serializes each request as it would for the wire, and nothing else is in
between. A gRPC server on
loopback costs about half a millisecond a call on this project's machines
(five seconds for a 10,000-call log); the channel costs a few microseconds.
"""

from __future__ import annotations

import asyncio
import inspect
import io
import time
from collections.abc import Callable, Iterator
from contextlib import redirect_stdout
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, cast

import grpc
import grpc.aio

from baton.controller.history import read_saved_log
from baton.controller.protocol import (
    ControllerProtocol,
    Diverged,
    Effect,
    Fenced,
    NonDeterminismError,
    ProtocolError,
    State,
    Unqueued,
)
from baton.controller.service import check_request
from baton.durability import held_whole
from baton.rpc.errors import StatusError, status_of
from baton.rpc.methods import describe_request as describe
from baton.rpc.methods import differing_fields, drone_api, path
from baton.sdk import aio
from baton.sdk.calls import PROGRAM_CALLS
from baton.sdk.drone import Drone
from baton.sdk.run import failure, load_mission, parse_params
from baton.v1 import drone_api_pb2, ring_pb2

# The replayer's id in its ring of one: no controller has it, so every message
# of the log is someone else's (handled, never taken for our own).
REPLAYER = -1
MISSION_DONE = path("ControllerRing.MissionDone")


class InconsistentLog(ValueError):
    """A log file that is not one ring's whole log (a gap, a framing that breaks)."""


class ReplayStopped(BaseException):
    """Ends the program at the first divergence.

    A BaseException, like SystemExit: a mission's ``except Exception`` must not
    swallow it and go on with a log it no longer follows.
    """


@dataclass(frozen=True)
class Divergence:
    """Where the program stopped following the log, both sides as readable text."""

    reqnr: int  # the request number at which they part
    why: str
    logged: str  # the log's request there ("" past its end)
    program: str  # the program's request there ("" once it ended)
    fields: tuple[str, ...] = ()  # the fields that differ, for the same method

    def lines(self) -> list[str]:
        """The divergence for a person, one fact a line."""
        lines = [f"diverged at request {self.reqnr}: {self.why}"]
        if self.logged:
            lines.append(f"  the log holds:    {self.logged}")
        if self.program:
            lines.append(f"  the program asks: {self.program}")
        if self.fields:
            lines.append(f"  fields that differ: {', '.join(self.fields)}")
        return lines


class LogReplay:
    """A replica's REPLAY state holding a whole saved log, answering calls from it."""

    def __init__(self, messages: list[ring_pb2.LogMessage], whole_up_to: int | None = None) -> None:
        # Set for a file its controller could not write to the end (``SavedLog``).
        self.whole_up_to = whole_up_to
        expected = list(range(1, len(messages) + 1))
        lognrs = [m.lognr for m in messages]
        if lognrs != expected:
            missing = sorted(set(range(1, max(lognrs, default=0) + 1)) - set(lognrs))
            raise InconsistentLog(
                f"the log lacks log messages {_ranges(missing)}: a controller's log is whole "
                "once its mission ended; this one was saved before, or by a controller still "
                "catching up (take another controller's)"
            )
        self.protocol = ControllerProtocol(REPLAYER, [REPLAYER], flush_limit=0)
        self.logged_reqnr = 0  # the last request the log holds
        self.divergence: Divergence | None = None
        for message in messages:
            try:
                self._check(self.protocol.on_log(message))
            except ProtocolError as exc:
                raise InconsistentLog(f"log message {message.lognr}: {exc}") from exc
            if message.entries:
                self.logged_reqnr = message.entries[-1].reqnr

    def _past_the_end(self) -> str:
        """Why the log holds no more: a file cut by a failed write says what it lacks."""
        ends = f"it ends at request {self.logged_reqnr}, in log message {self.protocol.lognr}"
        if self.whole_up_to is not None:
            return (
                f"the file holds only {held_whole(self.whole_up_to)} whole ({ends}): its "
                "controller could not write to it after that (its log and GetStatus name the "
                f"error), so what the ring logged after request {self.logged_reqnr} is missing "
                "here; replay another controller's log file"
            )
        return (
            f"the program asks for more than the log holds ({ends}: a file saved before "
            "the mission ended, or of a controller still catching up)"
        )

    @staticmethod
    def _check(effects: list[Effect]) -> None:
        for effect in effects:
            if isinstance(effect, Fenced | Diverged | Unqueued):
                raise InconsistentLog(
                    f"log message {effect.lognr} is not of the ring's log ({effect}): a log "
                    "file keeps only the framing the ring took, so this one was changed or "
                    "merged from two runs"
                )

    @property
    def replayed(self) -> int:
        """The requests answered from the log so far."""
        return self.protocol.replayed

    def answer(self, method: str, request: bytes) -> ring_pb2.LogEntry:
        """The logged entry for the program's next call; ``ReplayStopped`` at a divergence."""
        if self.protocol.state is not State.REPLAY:
            self._diverge(
                Divergence(
                    self.protocol.reqnr + 1, self._past_the_end(), "", describe(method, request)
                )
            )
        try:
            entry, effects = self.protocol.replay(method, request)
        except NonDeterminismError as exc:
            same = exc.logged_method == method
            self._diverge(
                Divergence(
                    exc.reqnr,
                    "the program asks for another request than the log holds",
                    describe(exc.logged_method, exc.logged_request),
                    describe(method, request),
                    tuple(differing_fields(method, exc.logged_request, request) if same else ()),
                )
            )
        self._check(effects)
        return entry

    def finish(self, ended: str) -> None:
        """The program ended (``ended`` says how): a divergence if the log holds more."""
        if self.divergence is not None or self.protocol.state is not State.REPLAY:
            return
        entry = self.protocol.log.entries[0]
        self.divergence = Divergence(
            entry.reqnr,
            f"the program {ended} after request {entry.reqnr - 1}; the log goes on to request "
            f"{self.logged_reqnr}",
            describe(entry.method, entry.request),
            "",
        )

    def _diverge(self, divergence: Divergence) -> None:
        self.divergence = divergence
        raise ReplayStopped(divergence.why)


def _ranges(numbers: list[int]) -> str:
    """1, 3-5, 9 (the first ten runs)."""
    runs: list[tuple[int, int]] = []
    for n in numbers:
        if runs and runs[-1][1] == n - 1:
            runs[-1] = (runs[-1][0], n)
        else:
            runs.append((n, n))
    text = ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs[:10])
    return text + (", ..." if len(runs) > 10 else "")


class ReplayedError(grpc.RpcError, grpc.Call):
    """A failed call's status as the log holds it (or as a controller refuses it)."""

    def __init__(self, code: grpc.StatusCode, details: str) -> None:
        super().__init__(details)
        self._code = code
        self._details = details

    def code(self) -> grpc.StatusCode:
        return self._code

    def details(self) -> str:
        return self._details

    def initial_metadata(self) -> tuple[()]:
        return ()

    def trailing_metadata(self) -> tuple[()]:
        return ()

    def is_active(self) -> bool:
        return False

    # grpc documents None for an RPC without a deadline; its stubs say float.
    def time_remaining(self) -> None:  # type: ignore[override]
        return None

    def cancel(self) -> bool:
        return False

    def add_callback(self, callback: Callable[[], None]) -> bool:
        return False


class _ReplayedCall(grpc.UnaryUnaryMultiCallable):
    """One drone-API method of a ``ReplayChannel``."""

    def __init__(
        self,
        replay: LogReplay,
        method: str,
        serialize: Callable[[Any], bytes] | None,
        deserialize: Callable[[bytes], Any] | None,
    ) -> None:
        self._replay = replay
        self._method = method
        self._serialize = serialize or bytes
        self._deserialize = deserialize or (lambda reply: reply)

    def __call__(self, request: Any, *args: Any, **kwargs: Any) -> Any:
        payload = self._serialize(request)
        if self._method == MISSION_DONE:
            return ring_pb2.MissionDoneReply(flushed=False, lognr=self._replay.protocol.lognr)
        found = drone_api().get(self._method)
        if found is None:
            raise ReplayedError(
                grpc.StatusCode.UNIMPLEMENTED,
                f"{self._method}: not a drone-API method; a replay answers the mission "
                "program's Mobility, Camera and Clock calls only",
            )
        try:
            check_request(self._method, found.request_type.FromString(payload))
        except StatusError as exc:  # refused before it takes a request number
            raise ReplayedError(exc.code, exc.message) from None
        entry = self._replay.answer(self._method, payload)
        if entry.status_code != 0:
            raise ReplayedError(status_of(entry.status_code), entry.status_message)
        return self._deserialize(entry.reply)

    def with_call(self, *args: Any, **kwargs: Any) -> Any:
        raise NotImplementedError("a replayed call has no Call object: call it plainly")

    def future(self, *args: Any, **kwargs: Any) -> Any:
        raise NotImplementedError("a mission program makes one call at a time: call it plainly")


class ReplayChannel(grpc.Channel):
    """A channel whose drone-API calls the log answers, in this process: no sockets.
    The SDK's stream of calls (``calls.PROGRAM_CALLS``) is answered call by call."""

    def __init__(self, replay: LogReplay) -> None:
        self._replay = replay

    def unary_unary(
        self,
        method: str,
        request_serializer: Callable[[Any], bytes] | None = None,
        response_deserializer: Callable[[bytes], Any] | None = None,
        _registered_method: bool | None = False,
    ) -> _ReplayedCall:
        return _ReplayedCall(self._replay, method, request_serializer, response_deserializer)

    def outcome(self, call: ring_pb2.ProgramCall) -> ring_pb2.ProgramOutcome:
        """A call on the program's stream of calls (``calls.PROGRAM_CALLS``), answered as
        its unary call is; ``ReplayStopped`` at a divergence."""
        try:
            reply = self.unary_unary(call.method)(call.request)
        except ReplayedError as exc:
            failure = drone_api_pb2.CallFailure(code=exc.code().value[0], message=exc.details())
            return ring_pb2.ProgramOutcome(call=call.call, failure=failure)
        return ring_pb2.ProgramOutcome(call=call.call, reply=reply)

    def stream_stream(  # type: ignore[override]
        self,
        method: str,
        request_serializer: Callable[[Any], bytes] | None = None,
        response_deserializer: Callable[[bytes], Any] | None = None,
        _registered_method: bool | None = False,
    ) -> Callable[..., Any]:
        if method != PROGRAM_CALLS:
            return self._streaming(method)
        return lambda requests, *args, **kwargs: _ReplayedStream(self, requests)

    def _streaming(self, method: str, *args: Any, **kwargs: Any) -> Callable[..., Any]:
        def refuse(*args: Any, **kwargs: Any) -> Any:
            raise ReplayedError(
                grpc.StatusCode.UNIMPLEMENTED,
                f"{method}: a replay answers the drone API's calls only",
            )

        return refuse

    # A refusing function stands for the other multi-callables: a replay has no such calls.
    unary_stream = stream_unary = _streaming  # type: ignore[assignment]

    def subscribe(self, callback: Callable[..., None], try_to_connect: bool = False) -> None:
        pass

    def unsubscribe(self, callback: Callable[..., None]) -> None:
        pass

    def close(self) -> None:
        pass

    def __enter__(self) -> ReplayChannel:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        pass


class _ReplayedStream:
    """The program's stream of calls on a ``ReplayChannel``: each call it sends, answered
    as it is taken (the blocking SDK sends one, then waits for its outcome)."""

    def __init__(self, channel: ReplayChannel, requests: Iterator[ring_pb2.ProgramCall]) -> None:
        self._channel = channel
        self._requests = requests

    def __iter__(self) -> _ReplayedStream:
        return self

    def __next__(self) -> ring_pb2.ProgramOutcome:
        return self._channel.outcome(next(self._requests))

    def cancel(self) -> bool:
        return False


class _AioReplayedStream:
    """The stream of calls on an ``AioReplayChannel``: a call's outcome when it is written."""

    def __init__(self, channel: ReplayChannel) -> None:
        self._channel = channel
        self._outcomes: list[ring_pb2.ProgramOutcome] = []

    async def write(self, call: ring_pb2.ProgramCall) -> None:
        self._outcomes.append(self._channel.outcome(call))

    async def read(self) -> ring_pb2.ProgramOutcome:
        return self._outcomes.pop(0)

    def cancel(self) -> bool:
        return False


class _AioReplayedCall:
    """One drone-API method of an ``AioReplayChannel``: the log's answer, awaited."""

    def __init__(self, call: _ReplayedCall) -> None:
        self._call = call

    async def __call__(self, request: Any, *args: Any, **kwargs: Any) -> Any:
        return self._call(request, *args, **kwargs)


class AioReplayChannel:
    """``ReplayChannel`` for the asyncio SDK (``baton.sdk.aio``)."""

    def __init__(self, replay: LogReplay) -> None:
        self._channel = ReplayChannel(replay)

    def unary_unary(
        self,
        method: str,
        request_serializer: Callable[[Any], bytes] | None = None,
        response_deserializer: Callable[[bytes], Any] | None = None,
        _registered_method: bool | None = False,
    ) -> _AioReplayedCall:
        return _AioReplayedCall(
            self._channel.unary_unary(method, request_serializer, response_deserializer)
        )

    def stream_stream(
        self,
        method: str,
        request_serializer: Callable[[Any], bytes] | None = None,
        response_deserializer: Callable[[bytes], Any] | None = None,
        _registered_method: bool | None = False,
    ) -> Callable[..., Any]:
        if method != PROGRAM_CALLS:
            return self._channel.stream_stream(method)
        return lambda *args, **kwargs: _AioReplayedStream(self._channel)

    async def close(self) -> None:
        pass


@dataclass(frozen=True)
class ReplayOutcome:
    """What replaying one log file came to."""

    path: Path
    logged: int  # requests the log holds
    replayed: int  # requests the program made that the log answered
    seconds: float
    divergence: Divergence | None = None
    program_error: str = ""  # what the program raised, if it raised
    output: str = ""  # what the program printed

    @property
    def clean(self) -> bool:
        """The program made exactly the log's requests, in order."""
        return self.divergence is None


def replay_log(path: Path, mission_file: str, pairs: list[str]) -> ReplayOutcome:
    """Replays the log file ``path`` against the mission file with its ``key=value`` parameters.

    Raises ``NotALogFile`` or ``InconsistentLog`` for a file that cannot be
    replayed, and ``SystemExit`` (from ``baton.sdk.run``) for a mission file or
    parameters that do not load.
    """
    started = time.perf_counter()
    saved = read_saved_log(path)
    replay = LogReplay(saved.messages, saved.whole_up_to)
    # Loaded anew for every log: module state of one replay must not leak into the next.
    mission = load_mission(mission_file)
    params = parse_params(mission, pairs)
    output = io.StringIO()
    with redirect_stdout(output):
        if inspect.iscoroutinefunction(mission):
            error = asyncio.run(_run_async(mission, params, replay, f"replay of {path}"))
        else:
            error = _run(mission, params, replay, f"replay of {path}")
    replay.finish(f"raised {error}" if error else "returned")
    return ReplayOutcome(
        path=path,
        logged=replay.logged_reqnr,
        replayed=replay.replayed,
        seconds=time.perf_counter() - started,
        divergence=replay.divergence,
        program_error=error,
        output=output.getvalue(),
    )


def _run(mission: Callable[..., Any], params: dict[str, Any], replay: LogReplay, name: str) -> str:
    """Runs a plain mission against the log; what it raised, if it raised."""
    drone = Drone(name, channel=ReplayChannel(replay))
    error = ""
    try:
        mission(drone, **params)
    except ReplayStopped:
        pass
    except Exception as exc:
        error = failure(exc)
    drone.close(error=error)
    return error


async def _run_async(
    mission: Callable[..., Any], params: dict[str, Any], replay: LogReplay, name: str
) -> str:
    """Runs an ``async def`` mission against the log; what it raised, if it raised."""
    drone = aio.Drone(name, channel=cast(grpc.aio.Channel, AioReplayChannel(replay)))
    error = ""
    try:
        await mission(drone, **params)
    except ReplayStopped:
        pass
    except Exception as exc:
        error = failure(exc)
    await drone.close(error=error)
    return error
