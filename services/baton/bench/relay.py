"""A bare gRPC relay: the floor under the controller's proxy overhead (``baton bench micro``).

    python -m baton.bench.relay UPSTREAM [--certs DIR --controller ID]

Serves every unary method on a loopback port and forwards each request's
bytes, unparsed, to the same method on ``UPSTREAM`` (the drone), with mutual
TLS as controller ``ID`` when ``--certs`` is given; the reply's bytes go back
as they came. It does what a controller's proxy cannot avoid (one more
process, one more Python gRPC server call and client call on loopback) and
nothing else: no token, no parsing, no log, no digest. Prints its address on
stdout once it serves, then runs until stdin closes or it is terminated.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from collections.abc import Awaitable, Callable

import grpc

from baton.rpc.channels import aio_channel
from baton.rpc.server import BatonServer, generic
from baton.rpc.tls import DRONE, Identity, Tls


class _Relay(grpc.GenericRpcHandler):
    def __init__(self, channel: grpc.aio.Channel) -> None:
        self._channel = channel
        self._handlers: dict[str, grpc.RpcMethodHandler] = {}

    def service(
        self, handler_call_details: grpc.HandlerCallDetails
    ) -> grpc.RpcMethodHandler | None:
        method = handler_call_details.method
        handler = self._handlers.get(method)
        if handler is None:
            handler = grpc.unary_unary_rpc_method_handler(self._forward(method))
            self._handlers[method] = handler
        return handler

    def _forward(
        self, method: str
    ) -> Callable[[bytes, grpc.aio.ServicerContext], Awaitable[bytes]]:
        upstream: grpc.aio.UnaryUnaryMultiCallable[bytes, bytes] = self._channel.unary_unary(method)

        async def forward(request: bytes, context: grpc.aio.ServicerContext) -> bytes:
            reply: bytes = await upstream(request)
            return reply

        return forward


async def serve(upstream: str, tls: Tls | None) -> None:
    """Relays until stdin closes."""
    channel = aio_channel(upstream, tls, DRONE if tls is not None else None)
    server = BatonServer("127.0.0.1:0", [generic(_Relay(channel))])
    await server.start()
    print(server.address, flush=True)
    loop = asyncio.get_running_loop()
    await loop.run_in_executor(None, sys.stdin.read)
    await server.stop(0)
    await channel.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("upstream")
    parser.add_argument("--certs", default=None)
    parser.add_argument("--controller", type=int, default=0)
    args = parser.parse_args()
    tls = None
    if args.certs is not None:
        tls = Tls.load(args.certs, Identity.controller(args.controller))
    asyncio.run(serve(args.upstream, tls))


if __name__ == "__main__":
    main()
