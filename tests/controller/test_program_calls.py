"""ControllerRing.ProgramCalls, the program's stream of calls, over real gRPC: bad input
gets its status and changes nothing; the stream goes on after a refused call."""

from __future__ import annotations

from collections.abc import AsyncIterator

import grpc
import grpc.aio
import pytest

from baton.bench.micro import _position_log, _replica
from baton.controller.node import ControllerNode
from baton.controller.service import ControllerRingService, mission_port
from baton.rpc.channels import aio_channel
from baton.rpc.methods import path
from baton.rpc.mission import MISSION_TOKEN_METADATA
from baton.rpc.server import BatonServer, servicer
from baton.v1 import drone_api_pb2 as api
from baton.v1 import ring_pb2, ring_pb2_grpc

TOKEN = "the-token"
GET_POSITION = path("Mobility.GetPosition")


@pytest.fixture
async def replica() -> AsyncIterator[tuple[ControllerNode, str]]:
    """A controller in REPLAY holding 5 logged GetPositions, its mission port served."""
    node = _replica()
    await node.on_log(_position_log(5))
    server = BatonServer("127.0.0.1:0", mission_port(node, TOKEN))
    await server.start()
    yield node, server.address
    await server.stop(0)
    await node.stop()


async def test_refused_calls_get_their_status_and_the_stream_goes_on(
    replica: tuple[ControllerNode, str],
) -> None:
    node, address = replica
    async with aio_channel(address) as channel:
        stream = ring_pb2_grpc.ControllerRingStub(channel).ProgramCalls(
            metadata=((MISSION_TOKEN_METADATA, TOKEN),)
        )
        calls = [
            ring_pb2.ProgramCall(call=1, method="/baton.v1.Mobility/Fly", request=b""),
            ring_pb2.ProgramCall(call=2, method=GET_POSITION, request=b"\xff\xff"),
            ring_pb2.ProgramCall(
                call=3,
                method=path("Clock.Sleep"),
                request=api.SleepRequest(seconds=-1).SerializeToString(),
            ),
            ring_pb2.ProgramCall(call=4, method=GET_POSITION, request=b""),
        ]
        outcomes: list[ring_pb2.ProgramOutcome] = []
        for call in calls:
            await stream.write(call)
            outcome = await stream.read()
            assert isinstance(outcome, ring_pb2.ProgramOutcome)
            outcomes.append(outcome)
        stream.cancel()
    assert [o.call for o in outcomes] == [1, 2, 3, 4]
    refused = [(grpc.StatusCode.UNIMPLEMENTED, "not a method of the drone API")]
    refused.append((grpc.StatusCode.INVALID_ARGUMENT, "payload is not a GetPositionRequest"))
    refused.append((grpc.StatusCode.INVALID_ARGUMENT, "seconds must be finite and >= 0"))
    for outcome, (code, words) in zip(outcomes[:3], refused, strict=True):
        assert outcome.failure.code == code.value[0], outcome
        assert words in outcome.failure.message
    # None of them took a request number: the fourth call is answered by the log's first.
    reply = api.GetPositionReply.FromString(outcomes[3].reply)
    assert reply.position.latitude_deg == pytest.approx(47.1)
    assert node.protocol.replayed == 1


async def test_a_stream_without_the_token_or_on_the_ring_port_is_refused(
    replica: tuple[ControllerNode, str],
) -> None:
    node, address = replica
    call = ring_pb2.ProgramCall(call=1, method=GET_POSITION, request=b"")
    async with aio_channel(address) as channel:
        stream = ring_pb2_grpc.ControllerRingStub(channel).ProgramCalls()
        with pytest.raises(grpc.aio.AioRpcError) as without:
            # Refused from the metadata, before the body is read: the refusal may end
            # the call before our write does.
            await stream.write(call)
            await stream.read()
    assert without.value.code() is grpc.StatusCode.PERMISSION_DENIED
    assert MISSION_TOKEN_METADATA in (without.value.details() or "")
    # The ring port's ControllerRing has no proxy: never the program's calls there.
    ring = ControllerRingService(node, TOKEN)
    add = ring_pb2_grpc.add_ControllerRingServicer_to_server
    server = BatonServer("127.0.0.1:0", [servicer("baton.v1.ControllerRing", add, ring)])
    await server.start()
    try:
        async with aio_channel(server.address) as channel:
            stream = ring_pb2_grpc.ControllerRingStub(channel).ProgramCalls(
                metadata=((MISSION_TOKEN_METADATA, TOKEN),)
            )
            with pytest.raises(grpc.aio.AioRpcError) as on_ring:
                await stream.write(call)
                await stream.read()
    finally:
        await server.stop(0)
    assert on_ring.value.code() is grpc.StatusCode.PERMISSION_DENIED
    assert "mission port" in (on_ring.value.details() or "")
    assert node.protocol.replayed == 0
