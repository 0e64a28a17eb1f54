"""InvokeStream, the drone calls a master sends as messages on one kept stream, and
the controller's side of it (``InvokeCalls``): each call must end as its unary Invoke
would, over real gRPC channels with the fake vehicle in-process."""

from __future__ import annotations

import asyncio
from typing import Any

import grpc
import pytest
from drone_harness import DroneUnderTest
from helpers.drone_calls import ARM, GOTO, POSITION, invoke
from waiting import eventually

from baton.controller.drone_link import InvokeCalls, refusal_of
from baton.logs import get_logger
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2

LOG = get_logger("test")


async def test_each_call_is_answered_by_its_number_and_a_refusal_ends_only_its_call(
    drone: DroneUnderTest,
) -> None:
    stream = drone.stub.InvokeStream()
    await stream.write(drone_pb2.InvokeCall(call=7, request=invoke(0, 1, POSITION)))
    first = await stream.read()
    assert isinstance(first, drone_pb2.InvokeOutcome)
    assert first.call == 7 and first.reply.reqnr == 1 and not first.reply.duplicate
    # Controller 2 is not the master: Invoke's FAILED_PRECONDITION and metadata.
    await stream.write(drone_pb2.InvokeCall(call=8, request=invoke(2, 2, ARM)))
    refused = await stream.read()
    assert isinstance(refused, drone_pb2.InvokeOutcome) and refused.call == 8
    assert refused.failure.code == grpc.StatusCode.FAILED_PRECONDITION.value[0]
    assert "master is controller 0" in refused.failure.message
    assert dict(refused.failure.metadata) == {
        "baton-master": "0",
        "baton-epoch": "1",
        "baton-after-reqnr": "1",
    }
    await stream.write(drone_pb2.InvokeCall(call=9, request=invoke(0, 2, ARM)))
    armed = await stream.read()
    assert isinstance(armed, drone_pb2.InvokeOutcome)
    assert armed.call == 9 and armed.reply.reqnr == 2
    await stream.done_writing()
    assert await stream.read() is grpc.aio.EOF
    assert drone.vehicle.calls == ["GetPosition", "Arm"]
    assert drone.service.seq.rejected == 1


async def test_a_refusal_raises_what_invoke_raises(drone: DroneUnderTest) -> None:
    calls = InvokeCalls(drone.stub, LOG)
    try:
        await calls.invoke(invoke(0, 1, POSITION), timeout_s=10)
        with pytest.raises(grpc.aio.AioRpcError) as info:
            await calls.invoke(invoke(0, 2, POSITION, epoch=7), timeout_s=10)
        with pytest.raises(grpc.aio.AioRpcError) as unary:
            await drone.stub.Invoke(invoke(0, 2, POSITION, epoch=7))
        assert info.value.code() == unary.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert info.value.details() == unary.value.details()
        with pytest.raises(grpc.aio.AioRpcError) as stale:
            await calls.invoke(invoke(1, 2, ARM), timeout_s=10)
        refusal = refusal_of(stale.value)
        assert refusal is not None and (refusal.master, refusal.epoch) == (0, 1)
        assert (await calls.invoke(invoke(0, 2, ARM), timeout_s=10)).reqnr == 2
    finally:
        await calls.close(1)


async def test_a_call_its_stream_left_runs_to_its_end_and_is_answered_again_from_the_cache(
    drone: DroneUnderTest,
) -> None:
    """As a cancelled Invoke's (issue 9, defect 1): the vehicle does it once."""
    drone.vehicle.gate = asyncio.Event()
    goto = invoke(0, 1, GOTO, api.GotoRequest(latitude_deg=47.4, longitude_deg=8.5))
    stream = drone.stub.InvokeStream()
    await stream.write(drone_pb2.InvokeCall(call=1, request=goto))
    await eventually(lambda: drone.vehicle.calls == ["Goto"], "the Goto executing")
    stream.cancel()
    drone.vehicle.gate.set()
    await eventually(lambda: drone.service.last_reqnr == 1, "the Goto recorded")
    calls = InvokeCalls(drone.stub, LOG)
    try:
        again = await calls.invoke(goto, timeout_s=10)
    finally:
        await calls.close(1)
    assert again.duplicate and drone.vehicle.calls == ["Goto"]
    assert [a.reqnr for a in drone.service.audit] == [1]


async def test_a_call_past_its_timeout_fails_and_the_next_call_opens_the_stream_again(
    drone: DroneUnderTest,
) -> None:
    calls = InvokeCalls(drone.stub, LOG)
    try:
        drone.vehicle.gate = asyncio.Event()
        goto = invoke(0, 1, GOTO, api.GotoRequest(latitude_deg=47.4, longitude_deg=8.5))
        with pytest.raises(grpc.aio.AioRpcError) as info:
            await calls.invoke(goto, timeout_s=0.3)
        assert info.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
        assert "request 1" in (info.value.details() or "")
        drone.vehicle.gate.set()
        again = await calls.invoke(goto, timeout_s=10)
        assert again.reqnr == 1 and drone.vehicle.calls == ["Goto"]
        assert (await calls.invoke(invoke(0, 2, POSITION), timeout_s=10)).reqnr == 2
    finally:
        await calls.close(1)


async def test_calls_in_flight_when_the_drone_goes_away_fail_unavailable() -> None:
    from drone_harness import start_drone

    drone, server = await start_drone()
    calls = InvokeCalls(drone.stub, LOG)
    try:
        await calls.invoke(invoke(0, 1, POSITION), timeout_s=10)
        drone.vehicle.gate = asyncio.Event()
        goto = invoke(0, 2, GOTO, api.GotoRequest(latitude_deg=47.4, longitude_deg=8.5))
        pending = asyncio.ensure_future(calls.invoke(goto, timeout_s=30))
        await eventually(lambda: "Goto" in drone.vehicle.calls, "the Goto executing")
        await server.stop(0)
        with pytest.raises(grpc.aio.AioRpcError) as info:
            await asyncio.wait_for(pending, 10)
        assert info.value.code() == grpc.StatusCode.UNAVAILABLE
    finally:
        drone.vehicle.gate = None
        await calls.close(1)


async def test_close_waits_for_the_call_in_flight(
    drone: DroneUnderTest, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A call in flight at a handover completes normally (footnote 2)."""
    calls = InvokeCalls(drone.stub, LOG)
    drone.vehicle.gate = asyncio.Event()
    goto = invoke(0, 1, GOTO, api.GotoRequest(latitude_deg=47.4, longitude_deg=8.5))
    pending = asyncio.ensure_future(calls.invoke(goto, timeout_s=30))
    await eventually(lambda: drone.vehicle.calls == ["Goto"], "the Goto executing")
    # The barrier: close has started waiting on the calls in flight. A close that
    # ended the stream instead never gets there (and this times out).
    waiting_on_calls = asyncio.Event()
    real_wait = asyncio.wait

    async def wait(*args: Any, **kwargs: Any) -> Any:
        waiting_on_calls.set()
        return await real_wait(*args, **kwargs)

    monkeypatch.setattr(asyncio, "wait", wait)
    closing = asyncio.ensure_future(calls.close(30))
    await asyncio.wait_for(waiting_on_calls.wait(), 10)
    assert not closing.done() and not pending.done()
    drone.vehicle.gate.set()
    assert (await asyncio.wait_for(pending, 10)).reqnr == 1
    await asyncio.wait_for(closing, 10)


async def test_a_call_written_on_a_stream_that_just_finished_fails_unavailable(
    drone: DroneUnderTest,
) -> None:
    """The stream ended (here: cancelled) and its reader has not taken it away yet: the
    next call's write meets a finished call (grpc's InvalidStateError, 'RPC already
    finished'). It fails as a dropped Invoke does, UNAVAILABLE (the program's call is
    sent again), not with an exception the call loop does not expect; sent again once
    the reader took the ended stream away, it goes on a new one."""
    calls = InvokeCalls(drone.stub, LOG)
    try:
        await calls.invoke(invoke(0, 1, POSITION), timeout_s=10)
        stream = calls._stream
        assert stream is not None
        stream.cancel()  # no await between: the reader has not run
        with pytest.raises(grpc.aio.AioRpcError) as info:
            await calls.invoke(invoke(0, 2, POSITION), timeout_s=10)
        assert info.value.code() == grpc.StatusCode.UNAVAILABLE, info.value
        # Sent again once the reader has taken the stream away, on a new one.
        await eventually(lambda: calls._stream is not stream, "the ended stream taken away")
        assert (await calls.invoke(invoke(0, 2, POSITION), timeout_s=10)).reqnr == 2
    finally:
        await calls.close(1)
