"""The channel to the drone a controller keeps connected for its next session."""

from __future__ import annotations

import grpc
from drone_harness import start_drone
from waiting import eventually

from baton.controller.drone_link import WarmChannel
from baton.rpc.streams import next_message
from baton.v1 import drone_pb2, drone_pb2_grpc


async def spare_connected(warm: WarmChannel) -> grpc.aio.Channel:
    """Starts ``warm`` and waits until its first spare is connected; returns it."""
    warm.start()
    spare = warm._spare
    assert spare is not None
    await eventually(
        lambda: spare.get_state() is grpc.ChannelConnectivity.READY, "the spare connected"
    )
    return spare


async def test_a_session_takes_the_channel_connected_in_advance_and_a_new_one_connects() -> None:
    drone, server = await start_drone()
    warm = WarmChannel(drone.address)
    try:
        spare = await spare_connected(warm)
        channel, connected = warm.take()
        assert channel is spare and connected
        # Taken at once (nothing awaited between), the next spare has usually not
        # connected yet: a fresh channel, and the spare that was not ready is closed,
        # not left. gRPC connects on its own thread, so on a quiet machine the spare may
        # be ready already: then it is the one taken, connected.
        unready = warm._spare
        assert unready is not None and unready is not spare
        fresh, connected = warm.take()
        if connected:
            assert fresh is unready
        else:
            assert fresh is not unready
            await eventually(
                lambda: unready.get_state() is grpc.ChannelConnectivity.SHUTDOWN,
                "the spare closed",
            )
        for taken in (channel, fresh):  # either works as it is
            call = drone_pb2_grpc.DroneStub(taken).Connect(
                drone_pb2.ConnectRequest(controller_id=0)
            )
            assert (await next_message(call)).HasField("connected")
            call.cancel()
        # the second take was warm exactly when its spare had connected in time
        assert (warm.warm, warm.cold) == ((2, 0) if connected else (1, 1))
        await channel.close()
        await fresh.close()
    finally:
        await warm.close()
        await server.stop()


async def test_a_spare_cut_off_from_the_drone_is_not_taken() -> None:
    drone, server = await start_drone()
    warm = WarmChannel(drone.address)
    try:
        spare = await spare_connected(warm)
        await server.stop()  # the drone goes: the spare's connection breaks
        await eventually(
            lambda: spare.get_state() is not grpc.ChannelConnectivity.READY, "the spare broken"
        )
        channel, connected = warm.take()
        assert channel is not spare and not connected
        await channel.close()
    finally:
        await warm.close()
