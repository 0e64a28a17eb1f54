"""The drone's standby streams over a real gRPC channel: who is reachable, and a
TakeOver that is owed to a taker whose stream was not there to carry it (issue 10)."""

from __future__ import annotations

import grpc
import pytest
from drone_harness import connect_as_master, start_drone

from baton.digest import request_digest
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2


async def test_a_standby_stream_says_who_is_master_and_counts_as_reachable() -> None:
    drone, server = await start_drone()
    try:
        call = drone.stub.Standby(drone_pb2.StandbyRequest(controller_id=2))
        first = await call.read()
        assert first.held.master == 0 and first.held.epoch == 1
        status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        assert list(status.reachable) == [2]
        call.cancel()
        with pytest.raises(grpc.aio.AioRpcError) as unknown:
            await drone.stub.Standby(drone_pb2.StandbyRequest(controller_id=7)).read()
        assert unknown.value.code() is grpc.StatusCode.INVALID_ARGUMENT
    finally:
        await server.stop()


async def test_a_takeover_is_told_again_to_a_taker_that_was_not_listening() -> None:
    drone, server = await start_drone()
    try:
        reply = await drone.stub.Handover(drone_pb2.HandoverRequest(new_master=1, takeover=True))
        assert reply.epoch == 2
        record = (await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())).handovers[0]
        assert (record.kind, record.trigger) == (
            drone_pb2.HANDOVER_KIND_TAKEOVER,
            drone_pb2.HANDOVER_TRIGGER_RPC,
        )
        # Controller 1 held no standby stream when the drone decided: it is told when
        # it opens one, for as long as it has not sent a request as master.
        call = drone.stub.Standby(drone_pb2.StandbyRequest(controller_id=1))
        assert (await call.read()).held.master == 1
        owed = (await call.read()).take_over
        assert (owed.old_master, owed.epoch) == (0, 2)
        call.cancel()
        other = drone.stub.Standby(drone_pb2.StandbyRequest(controller_id=2))
        assert (await other.read()).held.master == 1  # nothing owed to 2
        other.cancel()
    finally:
        await server.stop()


NOW = "/baton.v1.Clock/Now"
POSITION = "/baton.v1.Mobility/GetPosition"


def clock_reply(reqnr: int, method: str = NOW, seconds: float = 1.0) -> drone_pb2.RetainedReply:
    reply = api.NowReply(unix_time_s=1_700_000_000 + seconds).SerializeToString()
    return drone_pb2.RetainedReply(
        reqnr=reqnr, method=method, request_digest=request_digest(method, b""), reply=reply
    )


async def test_a_taker_connects_and_gets_the_retained_replies_above_what_it_holds() -> None:
    """F12: a lost master's Clock.Now, sent along with its next Invoke, reaches the taker
    with the drone's own replies above the watermark, so it reads the same time; only
    those above what the taker holds (its Connect says), so the link carries no more."""
    drone, server = await start_drone()
    try:
        first = drone_pb2.InvokeRequest(controller_id=0, reqnr=1, method=POSITION, epoch=1)
        await drone.stub.Invoke(first)
        read = clock_reply(2, seconds=12.5)
        second = drone_pb2.InvokeRequest(
            controller_id=0, reqnr=3, method=POSITION, epoch=1, master_answers=[read]
        )
        position = await drone.stub.Invoke(second)
        standby = drone.stub.Standby(drone_pb2.StandbyRequest(controller_id=1))
        await standby.read()
        await drone.stub.Handover(drone_pb2.HandoverRequest(new_master=1, takeover=True))
        take_over = (await standby.read()).take_over
        standby.cancel()
        assert (take_over.old_master, take_over.epoch, take_over.after_reqnr) == (0, 2, 3)
        connected, retained = await connect_as_master(drone.stub, 1, holds_reqnr=1)
        assert connected.epoch == 2
        assert [r.reqnr for r in retained] == [2, 3]
        assert retained[0] == read
        assert retained[1].reply == position.payload
        assert retained[1].request_digest == request_digest(POSITION, b"")
    finally:
        await server.stop()


async def test_every_connected_of_a_taker_says_takeover_and_the_watermark() -> None:
    """--lose-master seed 1092: a taker that sent a request, then rejoined with nothing,
    is told no TakeOver again; its Connected says the mastership is a takeover (no
    handover message will come) and the watermark it must hold before it goes ACTIVE
    (the retained replies start above it)."""
    drone, server = await start_drone()
    try:
        await drone.stub.Invoke(
            drone_pb2.InvokeRequest(controller_id=0, reqnr=1, method=POSITION, epoch=1)
        )
        await drone.stub.Handover(drone_pb2.HandoverRequest(new_master=1, takeover=True))
        await drone.stub.Invoke(
            drone_pb2.InvokeRequest(
                controller_id=1, reqnr=2, method=POSITION, epoch=2, watermark_reqnr=1
            )
        )
        connected, retained = await connect_as_master(drone.stub, 1, holds_reqnr=0)
        assert (connected.epoch, connected.takeover, connected.watermark_reqnr) == (2, True, 1)
        assert [r.reqnr for r in retained] == [2]
        await drone.stub.Handover(drone_pb2.HandoverRequest(new_master=2))
        connected, _ = await connect_as_master(drone.stub, 2)
        assert (connected.epoch, connected.takeover) == (3, False)
    finally:
        await server.stop()


@pytest.mark.parametrize(
    ("kept", "why"),
    [
        (clock_reply(2, method=POSITION), "neither a Clock method nor a call given up"),
        (clock_reply(1), "must increase, above the last request served (1)"),
        (clock_reply(3), "below this one (3)"),
    ],
)
async def test_a_clock_reply_sent_along_out_of_place_is_refused_and_nothing_runs(
    kept: drone_pb2.RetainedReply, why: str
) -> None:
    drone, server = await start_drone()
    try:
        await drone.stub.Invoke(
            drone_pb2.InvokeRequest(controller_id=0, reqnr=1, method=POSITION, epoch=1)
        )
        bad = drone_pb2.InvokeRequest(
            controller_id=0, reqnr=3, method=POSITION, epoch=1, master_answers=[kept]
        )
        with pytest.raises(grpc.aio.AioRpcError) as refused:
            await drone.stub.Invoke(bad)
        assert refused.value.code() is grpc.StatusCode.INVALID_ARGUMENT
        assert why in (refused.value.details() or "")
        status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        assert (status.last_reqnr, status.executed, status.retained_replies) == (1, 1, 1)
    finally:
        await server.stop()
