"""The drone's standby streams over a real gRPC channel: who is reachable, and a
TakeOver that is owed to a taker whose stream was not there to carry it (issue 10)."""

from __future__ import annotations

import grpc
import pytest
from drone_harness import start_drone

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
        assert (record.kind, record.trigger) == ("takeover", "rpc")
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
