"""Starting and stopping a baton gRPC server, the same way for every service.

Every server serves the standard health service and server reflection, so
``grpcurl HOST:PORT list`` and ``describe`` work on all of them (with the
TLS flags of docs/operating.md's "Inspecting with grpcurl", or ``-plaintext`` on an insecure
port).
"""

from __future__ import annotations

import inspect
import socket
from collections.abc import AsyncIterator, Awaitable, Callable, Iterable
from dataclasses import dataclass
from typing import Any, cast

import grpc
from google.protobuf.message import DecodeError
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from baton.rpc.channels import SERVER_OPTIONS
from baton.rpc.tls import Tls

# A grpc.aio server's method behaviour: a coroutine function, or an async generator
# of a stream's replies. grpc's stubs type RpcMethodHandler's as the blocking server's.
_AioBehaviour = Callable[[Any, grpc.aio.ServicerContext[Any, Any]], Any]


class MalformedRequests(grpc.aio.ServerInterceptor):
    """A request that does not parse as its method's message is INVALID_ARGUMENT
    naming the method, where gRPC would answer UNKNOWN (tests/test_fuzz.py
    checks it). Requests of a stream are parsed where they are read."""

    async def intercept_service(
        self,
        continuation: Callable[
            [grpc.HandlerCallDetails], Awaitable[grpc.RpcMethodHandler[Any, Any] | None]
        ],
        details: grpc.HandlerCallDetails,
    ) -> grpc.RpcMethodHandler[Any, Any] | None:
        handler = await continuation(details)
        if handler is None or handler.request_streaming or handler.request_deserializer is None:
            return handler
        parse = handler.request_deserializer
        method = details.method

        async def parsed(raw: bytes, context: grpc.aio.ServicerContext) -> Any:
            try:
                return parse(raw)
            except DecodeError as exc:
                await context.abort(
                    grpc.StatusCode.INVALID_ARGUMENT,
                    f"{method}: the request is not a valid message of this method: {exc}",
                )

        if handler.response_streaming:
            streaming = cast(_AioBehaviour, handler.unary_stream)
            # A stream's servicer yields its replies, or writes them (context.write)
            # as the health service's Watch does: the wrapper must do the same.
            if inspect.isasyncgenfunction(streaming):

                async def yielding(raw: bytes, context: grpc.aio.ServicerContext) -> AsyncIterator:
                    async for reply in streaming(await parsed(raw, context), context):
                        yield reply

                behavior: Callable[..., Any] = yielding
            else:

                async def writing(raw: bytes, context: grpc.aio.ServicerContext) -> None:
                    await streaming(await parsed(raw, context), context)

                behavior = writing
            return grpc.unary_stream_rpc_method_handler(
                behavior, response_serializer=handler.response_serializer
            )
        unary = cast(_AioBehaviour, handler.unary_unary)

        async def unary_unary(raw: bytes, context: grpc.aio.ServicerContext) -> Any:
            return await unary(await parsed(raw, context), context)

        return grpc.unary_unary_rpc_method_handler(
            unary_unary, response_serializer=handler.response_serializer
        )


def _why_not_bound(address: str) -> str:
    """Why gRPC could not bind ``address`` (it only says it failed)."""
    host = address.rsplit(":", 1)[0].strip("[]")
    try:
        socket.getaddrinfo(host, None)
    except socket.gaierror:
        return (
            f"cannot serve on {address}: the host {host!r} does not resolve; give an address "
            "of this machine (127.0.0.1, 0.0.0.0 or a name it resolves)"
        )
    return (
        f"cannot serve on {address}: the address is in use or not on this host; "
        "choose another port (port 0 picks a free one)"
    )


@dataclass(frozen=True)
class Servicer:
    """One thing a ``BatonServer`` serves: the service names it reports SERVING and
    lists for reflection, and how it is added to the gRPC server (``servicer``,
    ``generic``)."""

    names: tuple[str, ...]
    add: Callable[[grpc.aio.Server], None]


def servicer(
    name: str, add_to_server: Callable[[Any, grpc.aio.Server], None], impl: Any
) -> Servicer:
    """Service ``name`` (``baton.v1.Drone``) served by ``impl`` through its generated
    ``add_..._to_server``."""
    return Servicer((name,), lambda server: add_to_server(impl, server))


def generic(handler: grpc.GenericRpcHandler, *names: str) -> Servicer:
    """A generic handler (a proxy, a relay) serving the services ``names``."""
    return Servicer(names, lambda server: server.add_generic_rpc_handlers((handler,)))


class BatonServer:
    """A ``grpc.aio`` server with health and reflection, bound to one address, serving
    the servicers it is given."""

    def __init__(
        self,
        address: str,
        servicers: Iterable[Servicer],
        keepalive: tuple[float, float] | None = None,
        tls: Tls | None = None,
    ) -> None:
        """``keepalive`` (ping every so many seconds, give up after so many without the
        answer) overrides the project's 10 s and 5 s (channels.py) for a server that
        must notice a silent client sooner. With ``tls`` the port takes only callers
        with a certificate of the mission's CA (tls.py); without, anyone."""
        options = dict(SERVER_OPTIONS)
        if keepalive is not None:
            every_ms, timeout_ms = round(keepalive[0] * 1000), round(keepalive[1] * 1000)
            options["grpc.keepalive_time_ms"] = every_ms
            options["grpc.http2.min_time_between_pings_ms"] = every_ms
            options["grpc.keepalive_timeout_ms"] = timeout_ms
            options["grpc.http2.ping_timeout_ms"] = timeout_ms
        self._server = grpc.aio.server(
            options=list(options.items()), interceptors=[MalformedRequests()]
        )
        self.health = health.aio.HealthServicer()
        health_pb2_grpc.add_HealthServicer_to_server(self.health, self._server)
        self.service_names: list[str] = []
        for served in servicers:
            served.add(self._server)
            self.service_names += served.names
        reflection.enable_server_reflection(
            [*self.service_names, health.SERVICE_NAME, reflection.SERVICE_NAME], self._server
        )
        try:
            if tls is None:
                self.port = self._server.add_insecure_port(address)
            else:
                self.port = self._server.add_secure_port(address, tls.server_credentials())
        except RuntimeError:  # grpcio's way of saying the bind failed
            self.port = 0
        if self.port == 0:
            raise OSError(_why_not_bound(address))
        host = address.rsplit(":", 1)[0]
        self.address = f"{host}:{self.port}"

    async def start(self) -> None:
        """Starts serving and reports every service SERVING."""
        await self._server.start()
        for name in ["", *self.service_names]:
            await self.health.set(name, health_pb2.HealthCheckResponse.SERVING)

    async def stop(self, grace: float = 1.0) -> None:
        """Reports NOT_SERVING, then stops, letting calls finish for ``grace`` seconds."""
        await self.health.enter_graceful_shutdown()
        await self._server.stop(grace)
