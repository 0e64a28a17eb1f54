"""Every port's gate: the caller is admitted before its request is read, and a
revoked certificate's live streams are cut (the decisions: admission.py).

grpc.aio reads a unary request whole before any of our code sees the call,
and a server interceptor sees the method and metadata only, not the peer's
certificate (grpc/grpc#18459). So the gate serves every method as
request-streaming, which is the same on the wire: its behaviour runs as the
call arrives, asks the auth context who calls, decides, and only then reads
the one request (``context.read``). A request that does not parse is
INVALID_ARGUMENT naming the method, where gRPC would answer UNKNOWN
(tests/drone/test_fuzz.py checks it); the requests of a stream are parsed
where the servicer reads them.

A call on a request or reply stream runs as a task the gate can end: when a
newer revocation list names its certificate (a timer re-reads the list every
``RECHECK_S``), or the certificate expires while the stream is open (gRPC
checks validity at the handshake only), the task is cancelled and the stream
ends UNAUTHENTICATED. A unary call runs to its end; the caller's next call
is refused.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import inspect
import math
import time
from collections import Counter
from collections.abc import AsyncGenerator, Awaitable, Callable, Hashable
from dataclasses import dataclass
from typing import Any, TypeVar, cast

import grpc
from cryptography import x509
from google.protobuf.message import DecodeError

from baton.logs import get_logger
from baton.rpc.admission import (
    RECHECK_S,
    Caller,
    PortPolicy,
    admit,
    invalid_error,
    port_full,
    to_cut,
)
from baton.rpc.errors import StatusError, abort_with
from baton.rpc.mission import mission_in
from baton.rpc.revocation import REVOKED_CRL, RevocationList
from baton.rpc.tls import Tls, caller

# How often a port refusing calls for being full says so, at most.
FULL_LOG_EVERY_S = 10.0
# A grpc.aio server's method behaviour: a coroutine function, or an async generator
# of a stream's replies. grpc's stubs type RpcMethodHandler's as the blocking server's.
_AioBehaviour = Callable[[Any, grpc.aio.ServicerContext[Any, Any]], Any]
_Continuation = Callable[
    [grpc.HandlerCallDetails], Awaitable["grpc.RpcMethodHandler[Any, Any] | None"]
]


@functools.lru_cache(maxsize=256)
def _serial_and_end(pem: bytes) -> tuple[int | None, float | None]:
    try:
        cert = x509.load_pem_x509_certificate(pem)
    except ValueError:
        return None, None
    return cert.serial_number, cert.not_valid_after_utc.timestamp()


def caller_of(context: grpc.aio.ServicerContext[Any, Any]) -> Caller:
    """Who calls: the identity, serial and validity of the certificate gRPC verified."""
    pems = list(context.auth_context().get("x509_pem_cert", ()))
    serial, not_after = _serial_and_end(bytes(pems[0])) if pems else (None, None)
    return Caller(caller(context), serial, not_after)


K = TypeVar("K", bound=Hashable)


def _release(counter: Counter[K], key: K) -> None:
    """One call of ``key`` fewer in flight; a key with none left is dropped."""
    counter[key] -= 1
    if counter[key] <= 0:
        del counter[key]


@dataclass
class _Live:
    caller: Caller
    cut: asyncio.Event


class Gate(grpc.aio.ServerInterceptor):
    """Admits each call of a port by ``policy`` (with ``tls``; an insecure port
    admits everyone) before its request is read, and cuts revoked streams."""

    def __init__(self, policy: PortPolicy, tls: Tls | None) -> None:
        self.policy = policy
        self.enforced = tls is not None
        self.revocations = (
            RevocationList(tls.folder / REVOKED_CRL, tls.ca)
            if tls is not None and tls.folder is not None
            else None
        )
        self.log = get_logger("gate").bind(port=policy.name)
        # Calls in flight by caller and the mission it names (None on a port of one
        # mission), and by caller.
        self._in_flight: Counter[tuple[Caller, str | None]] = Counter()
        self._in_flight_all: Counter[Caller] = Counter()
        # Calls in flight on the port, whoever makes them; the calls refused for a full
        # port since it last said so, and when (``admission.port_full``).
        self._on_port = 0
        self._full_refusals = 0
        self._full_said_at = -math.inf
        self._live: dict[int, _Live] = {}
        self._next = 0
        # Told the revocation list's serials after every refresh (a controller's log
        # message keys follow it: controller/peer_keys.py).
        self.on_refresh: Callable[[frozenset[int]], None] | None = None
        self.refresh()

    def refresh(self) -> None:
        """Reads the revocation list again if it changed, and cuts the live streams
        whose certificates it revokes or which have expired."""
        if self.revocations is None:
            return
        before = self.revocations.serials
        problem = self.revocations.refresh()
        if problem is not None:
            self.log.error("revocation list not read", reason=problem)
        if self.revocations.serials != before:
            self.log.warning(
                "revocation list read", revoked=sorted(f"{s:x}" for s in self.revocations.serials)
            )
        live = {key: call.caller for key, call in self._live.items()}
        for key in to_cut(live, self.revocations.serials, time.time()):
            self._live[key].cut.set()
        if self.on_refresh is not None:
            self.on_refresh(self.revocations.serials)

    def _revoked(self) -> frozenset[int]:
        return self.revocations.serials if self.revocations is not None else frozenset()

    async def watch(self) -> None:
        """Every RECHECK_S: the revocation list re-read and the live streams re-checked."""
        while True:
            await asyncio.sleep(RECHECK_S)
            self.refresh()

    async def intercept_service(
        self, continuation: _Continuation, details: grpc.HandlerCallDetails
    ) -> grpc.RpcMethodHandler[Any, Any] | None:
        handler = await continuation(details)
        if handler is None:
            return None
        method = details.method
        if handler.request_streaming:
            return self._stream_request(method, handler)
        return self._unary_request(method, handler)

    async def _serve(
        self,
        method: str,
        context: grpc.aio.ServicerContext[Any, Any],
        run: Callable[[], Awaitable[Any]],
        stream: bool,
    ) -> Any:
        """Runs ``run`` (which reads the request) if the port has room and the caller is
        admitted; a stream as a task that a revocation ends."""
        full = port_full(self.policy, method, self._on_port)
        if full is not None:
            self._refused_full(full)
            await abort_with(context, full)
        self._on_port += 1
        try:
            if not self.enforced:
                return await run()
            return await self._admitted(method, context, run, stream)
        finally:
            self._on_port -= 1

    def _refused_full(self, refusal: StatusError) -> None:
        """Counts a call refused for a full port, and says so at once, then at most every
        ``FULL_LOG_EVERY_S`` with the count: a flood of refusals is not a flood of lines."""
        self._full_refusals += 1
        now = time.monotonic()
        if now - self._full_said_at >= FULL_LOG_EVERY_S:
            self.log.warning(
                "calls refused before their requests: the port is full",
                reason=refusal.message,
                refused=self._full_refusals,
            )
            self._full_refusals, self._full_said_at = 0, now

    async def _admitted(
        self,
        method: str,
        context: grpc.aio.ServicerContext[Any, Any],
        run: Callable[[], Awaitable[Any]],
        stream: bool,
    ) -> Any:
        """Runs ``run`` if the caller's certificate admits it (``admission.admit``)."""
        who = caller_of(context)
        # Only a port of many missions counts per mission: elsewhere a caller naming
        # missions of its own choosing would take the cap again with each.
        many = self.policy.calls_per_caller_all_missions is not None
        key = (who, mission_in(context.invocation_metadata()) if many else None)
        revoked = self._revoked()
        refusal = admit(
            self.policy,
            method,
            who,
            revoked,
            self._in_flight[key],
            time.time(),
            self._in_flight_all[who],
        )
        if refusal is not None:
            self.log.warning(
                "call refused before its request", method=method, reason=refusal.message
            )
            await abort_with(context, refusal)
        self._in_flight[key] += 1
        self._in_flight_all[who] += 1
        try:
            if not stream:
                return await run()
            return await self._until_cut(method, context, who, run)
        finally:
            _release(self._in_flight, key)
            _release(self._in_flight_all, who)

    async def _until_cut(
        self,
        method: str,
        context: grpc.aio.ServicerContext[Any, Any],
        who: Caller,
        run: Callable[[], Awaitable[Any]],
    ) -> Any:
        key, self._next = self._next, self._next + 1
        live = self._live[key] = _Live(who, asyncio.Event())
        task = asyncio.ensure_future(run())
        cut = asyncio.ensure_future(live.cut.wait())
        try:
            await asyncio.wait({task, cut}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            del self._live[key]
            cut.cancel()
            if not task.done():
                task.cancel()
                with contextlib.suppress(BaseException):
                    await task
        if task.cancelled():
            why = who.invalid(self._revoked(), time.time()) or "no longer counts"
            error = invalid_error(method.rsplit("/", 1)[-1], who, why)
            self.log.warning("stream cut", method=method, reason=error.message)
            await abort_with(context, error)
        return task.result()

    def _unary_request(
        self, method: str, handler: grpc.RpcMethodHandler[Any, Any]
    ) -> grpc.RpcMethodHandler[Any, Any]:
        parse = handler.request_deserializer

        async def request(context: grpc.aio.ServicerContext[Any, Any]) -> Any:
            raw = await context.read()
            if raw is grpc.aio.EOF:
                await context.abort(
                    grpc.StatusCode.INVALID_ARGUMENT, f"{method}: the call carried no request"
                )
            if parse is None:
                return raw
            try:
                return parse(raw)
            except DecodeError as exc:
                await context.abort(
                    grpc.StatusCode.INVALID_ARGUMENT,
                    f"{method}: the request is not a valid message of this method: {exc}",
                )

        if not handler.response_streaming:
            unary = cast(_AioBehaviour, handler.unary_unary)

            async def unary_unary(_: object, context: grpc.aio.ServicerContext[Any, Any]) -> Any:
                async def run() -> Any:
                    return await unary(await request(context), context)

                return await self._serve(method, context, run, stream=False)

            return grpc.stream_unary_rpc_method_handler(
                unary_unary, response_serializer=handler.response_serializer
            )
        replies = _writing(cast(_AioBehaviour, handler.unary_stream))

        async def unary_stream(_: object, context: grpc.aio.ServicerContext[Any, Any]) -> None:
            async def run() -> None:
                await replies(await request(context), context)

            await self._serve(method, context, run, stream=True)

        return grpc.stream_stream_rpc_method_handler(
            unary_stream, response_serializer=handler.response_serializer
        )

    def _stream_request(
        self, method: str, handler: grpc.RpcMethodHandler[Any, Any]
    ) -> grpc.RpcMethodHandler[Any, Any]:
        if not handler.response_streaming:
            unary = cast(_AioBehaviour, handler.stream_unary)

            async def stream_unary(requests: Any, context: grpc.aio.ServicerContext) -> Any:
                return await self._serve(
                    method, context, lambda: unary(requests, context), stream=True
                )

            return grpc.stream_unary_rpc_method_handler(
                stream_unary,
                request_deserializer=handler.request_deserializer,
                response_serializer=handler.response_serializer,
            )
        replies = _writing(cast(_AioBehaviour, handler.stream_stream))

        async def stream_stream(requests: Any, context: grpc.aio.ServicerContext) -> None:
            await self._serve(method, context, lambda: replies(requests, context), stream=True)

        return grpc.stream_stream_rpc_method_handler(
            stream_stream,
            request_deserializer=handler.request_deserializer,
            response_serializer=handler.response_serializer,
        )


def _writing(
    behaviour: _AioBehaviour,
) -> Callable[[Any, grpc.aio.ServicerContext[Any, Any]], Awaitable[None]]:
    """A reply-stream behaviour as one that writes its replies (context.write): a
    servicer may yield them or write them, as the health service's Watch does, and
    the gate runs either as a task it can cancel."""
    if not inspect.isasyncgenfunction(behaviour):
        return cast(Callable[[Any, grpc.aio.ServicerContext[Any, Any]], Awaitable[None]], behaviour)

    async def write(request: Any, context: grpc.aio.ServicerContext[Any, Any]) -> None:
        # Closed when the write loop ends however it ends (a cancelled call too), so
        # that the servicer's clean-up runs then, not when the generator is collected.
        generator = cast(AsyncGenerator[Any, None], behaviour(request, context))
        async with contextlib.aclosing(generator) as replies:
            async for reply in replies:
                await context.write(reply)

    return write
