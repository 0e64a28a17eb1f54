"""Writing on a stream that ended (``rpc/streams.py`` ``write_message``): the call's
status, as every other end of a stream is said, over a real grpc stream."""

from __future__ import annotations

import grpc
import pytest

from baton.rpc.server import BatonServer, servicer
from baton.rpc.streams import next_message, write_message
from baton.v1 import ring_pb2, ring_pb2_grpc


class Ending(ring_pb2_grpc.ControllerRingServicer):
    """Says hello, then ends the stream with ``code`` (OK: returns)."""

    def __init__(self, code: grpc.StatusCode) -> None:
        self.code = code

    async def LogRing(self, request_iterator, context):  # type: ignore[no-untyped-def, override]
        await context.write(ring_pb2.LogAck(hello=True))
        if self.code is not grpc.StatusCode.OK:
            await context.abort(self.code, "ended here")


@pytest.mark.parametrize(
    ("ended", "said", "details"),
    [
        (grpc.StatusCode.RESOURCE_EXHAUSTED, grpc.StatusCode.RESOURCE_EXHAUSTED, "ended here"),
        (grpc.StatusCode.OK, grpc.StatusCode.UNAVAILABLE, "the peer ended the stream"),
    ],
)
async def test_a_write_on_a_finished_call_raises_its_status(
    ended: grpc.StatusCode, said: grpc.StatusCode, details: str
) -> None:
    impl = Ending(ended)  # type: ignore[abstract]
    ring = servicer(
        "baton.v1.ControllerRing", ring_pb2_grpc.add_ControllerRingServicer_to_server, impl
    )
    server = BatonServer("127.0.0.1:0", [ring])
    await server.start()
    try:
        async with grpc.aio.insecure_channel(server.address) as channel:
            call = ring_pb2_grpc.ControllerRingStub(channel).LogRing()
            assert (await next_message(call)).hello
            await call.code()  # the RPC finished: a plain write raises InvalidStateError
            with pytest.raises(grpc.aio.AioRpcError) as raised:
                await write_message(call, ring_pb2.LogFrame(lognr=1))
            assert (raised.value.code(), raised.value.details()) == (said, details)
    finally:
        await server.stop(0)
