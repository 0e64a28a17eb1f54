"""Starting and stopping a baton gRPC server, the same way for every service.

Every server serves the standard health service and server reflection, so
``grpcurl HOST:PORT list`` and ``describe`` work on all of them (with the
TLS flags of docs/operating.md's "Inspecting with grpcurl", or ``-plaintext`` on an insecure
port).
"""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from baton.rpc.admission import PortPolicy
from baton.rpc.channels import MAX_MESSAGE_BYTES, SERVER_OPTIONS
from baton.rpc.gate import Gate
from baton.rpc.tls import Tls


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
        policy: PortPolicy | None = None,
    ) -> None:
        """``keepalive`` (ping every so many seconds, give up after so many without the
        answer) overrides the project's 10 s and 5 s (channels.py) for a server that
        must notice a silent client sooner. With ``tls`` the port takes only callers
        with a certificate of the mission's CA (tls.py), not revoked, admitted by
        ``policy`` before their requests are read (gate.py); without, anyone. The
        policy's ``max_request_bytes`` bounds every request (by default the largest
        message of channels.py)."""
        policy = policy or PortPolicy(f"port {address}", MAX_MESSAGE_BYTES)
        options = dict(SERVER_OPTIONS)
        options["grpc.max_receive_message_length"] = policy.max_request_bytes
        if keepalive is not None:
            every_ms, timeout_ms = round(keepalive[0] * 1000), round(keepalive[1] * 1000)
            options["grpc.keepalive_time_ms"] = every_ms
            options["grpc.http2.min_time_between_pings_ms"] = every_ms
            options["grpc.keepalive_timeout_ms"] = timeout_ms
            options["grpc.http2.ping_timeout_ms"] = timeout_ms
        self.gate = Gate(policy, tls)
        self._server = grpc.aio.server(options=list(options.items()), interceptors=[self.gate])
        self._watching: asyncio.Task[None] | None = None
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
        if self.gate.revocations is not None:
            self._watching = asyncio.create_task(self.gate.watch(), name="revocations")
        for name in ["", *self.service_names]:
            await self.health.set(name, health_pb2.HealthCheckResponse.SERVING)

    async def stop(self, grace: float = 1.0) -> None:
        """Reports NOT_SERVING, then stops, letting calls finish for ``grace`` seconds."""
        await self.health.enter_graceful_shutdown()
        if self._watching is not None:
            self._watching.cancel()
        await self._server.stop(grace)
