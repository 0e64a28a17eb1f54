"""The Drone service over real gRPC channels, with the fake vehicle in-process."""

from __future__ import annotations

import asyncio

import grpc
import pytest
from drone_harness import DroneUnderTest, start_drone
from helpers.drone_calls import ARM, GOTO, POSITION, TAKEOFF, expect_error, invoke
from waiting import eventually

from baton.rpc.streams import next_message, read_message
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2


def trailing(error: grpc.aio.AioRpcError) -> dict[str, str | bytes]:
    return {k: v for k, v in (error.trailing_metadata() or ())}


async def test_master_invokes_in_order(drone: DroneUnderTest) -> None:
    reply = await drone.stub.Invoke(invoke(0, 1, POSITION))
    assert reply.reqnr == 1 and not reply.duplicate
    assert api.GetPositionReply.FromString(reply.payload).position.latitude_deg == pytest.approx(
        47.397742
    )
    await drone.stub.Invoke(invoke(0, 2, ARM))
    await drone.stub.Invoke(invoke(0, 3, TAKEOFF, api.TakeoffRequest(altitude_m=10)))
    status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest(include_audit=True))
    assert (status.last_reqnr, status.executed, status.master) == (3, 3, 0)
    assert [a.method for a in status.audit] == [POSITION, ARM, TAKEOFF]
    assert status.position.relative_altitude_m == 10
    assert status.flight_state.armed and status.flight_state.in_air
    assert list(status.controllers) == [0, 1, 2]
    assert status.vehicle_connected and status.vehicle_url == "fake://vehicle"


async def test_non_master_is_refused_with_master_metadata(drone: DroneUnderTest) -> None:
    await drone.stub.Invoke(invoke(0, 1, POSITION))
    error = await expect_error(
        drone.stub.Invoke(invoke(2, 2, ARM)), grpc.StatusCode.FAILED_PRECONDITION
    )
    assert "master is controller 0" in (error.details() or "")
    assert trailing(error) == {"baton-master": "0", "baton-epoch": "1", "baton-after-reqnr": "1"}
    assert "Arm" not in drone.vehicle.calls
    assert (await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())).rejected == 1


async def test_duplicate_answered_from_cache_and_executed_once(drone: DroneUnderTest) -> None:
    first = await drone.stub.Invoke(invoke(0, 1, ARM))
    again = await drone.stub.Invoke(invoke(0, 1, ARM))
    assert again.duplicate and again.payload == first.payload and again.reqnr == 1
    assert drone.vehicle.calls.count("Arm") == 1
    status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest(include_audit=True))
    assert (status.executed, status.duplicates, len(status.audit)) == (1, 1, 1)


async def test_duplicate_with_another_request_is_refused(drone: DroneUnderTest) -> None:
    await drone.stub.Invoke(invoke(0, 1, ARM))
    error = await expect_error(
        drone.stub.Invoke(invoke(0, 1, POSITION)), grpc.StatusCode.FAILED_PRECONDITION
    )
    assert "served as /baton.v1.Mobility/Arm" in (error.details() or "")
    assert "re-sent as /baton.v1.Mobility/GetPosition" in (error.details() or "")


async def test_request_numbers_may_skip_but_never_go_back(drone: DroneUnderTest) -> None:
    # The controller logs Clock.Now under a reqnr of its own: the drone never sees it.
    await drone.stub.Invoke(invoke(0, 2, POSITION))
    await drone.stub.Invoke(invoke(0, 5, POSITION))
    error = await expect_error(
        drone.stub.Invoke(invoke(0, 4, POSITION)), grpc.StatusCode.FAILED_PRECONDITION
    )
    assert "expected a reqnr above 5" in (error.details() or "")
    assert trailing(error)["baton-after-reqnr"] == "5"


async def test_a_request_number_far_ahead_is_refused_and_blocks_nothing(
    drone: DroneUnderTest,
) -> None:
    """Issue 9, defect 5: reqnr 2**64-1 used to be accepted, and every later request refused."""
    await drone.stub.Invoke(invoke(0, 1, POSITION))
    error = await expect_error(
        drone.stub.Invoke(invoke(0, 2**64 - 1, POSITION)), grpc.StatusCode.FAILED_PRECONDITION
    )
    assert "more than 1000000 above the last one served (1)" in (error.details() or "")
    assert (await drone.stub.Invoke(invoke(0, 2, POSITION))).reqnr == 2
    assert (await drone.stub.Invoke(invoke(0, 1_000_002, POSITION))).reqnr == 1_000_002


async def test_reqnr_zero_is_invalid(drone: DroneUnderTest) -> None:
    await expect_error(drone.stub.Invoke(invoke(0, 0, POSITION)), grpc.StatusCode.INVALID_ARGUMENT)


@pytest.mark.parametrize(
    ("method", "payload", "code", "detail"),
    [
        ("/baton.v1.Mobility/Fly", b"", grpc.StatusCode.UNIMPLEMENTED, "unknown drone-API method"),
        ("/baton.v1.Clock/Now", b"", grpc.StatusCode.UNIMPLEMENTED, "Clock is answered by"),
        (
            TAKEOFF,
            b"\xff\xff",
            grpc.StatusCode.INVALID_ARGUMENT,
            "is not a baton.v1.TakeoffRequest",
        ),
        (
            "/baton.v1.Camera/SetResolution",
            api.SetResolutionRequest(width=8, height=8).SerializeToString(),
            grpc.StatusCode.INVALID_ARGUMENT,
            "width 8 is out of range",
        ),
        (TAKEOFF, b"", grpc.StatusCode.ABORTED, "not armed"),
    ],
)
async def test_failed_requests_use_their_reqnr_and_replay_their_failure(
    drone: DroneUnderTest, method: str, payload: bytes, code: grpc.StatusCode, detail: str
) -> None:
    request = drone_pb2.InvokeRequest(
        controller_id=0, reqnr=1, method=method, payload=payload, epoch=1
    )
    error = await expect_error(drone.stub.Invoke(request), code)
    assert detail in (error.details() or "")
    assert "baton-master" not in trailing(error)
    again = await expect_error(drone.stub.Invoke(request), code)
    assert again.details() == error.details() and trailing(again)["baton-duplicate"] == "true"
    assert (await drone.stub.Invoke(invoke(0, 2, POSITION))).reqnr == 2


async def test_vehicle_not_connected_is_unavailable(drone: DroneUnderTest) -> None:
    drone.vehicle.is_connected = False
    await expect_error(drone.stub.Invoke(invoke(0, 1, POSITION)), grpc.StatusCode.UNAVAILABLE)
    status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
    assert not status.vehicle_connected and status.position.latitude_deg == 0


async def test_take_picture_through_invoke(drone: DroneUnderTest) -> None:
    reply = await drone.stub.Invoke(invoke(0, 1, "/baton.v1.Camera/TakePicture"))
    picture = api.TakePictureReply.FromString(reply.payload)
    assert (picture.width, picture.height, picture.sequence) == (64, 48, 1)
    assert len(picture.image) == len(b"P6\n64 48\n255\n") + 64 * 48 * 3
    assert picture.position.latitude_deg == pytest.approx(47.397742)


async def next_event(
    stream: grpc.aio.UnaryStreamCall[drone_pb2.ConnectRequest, drone_pb2.DroneEvent],
) -> drone_pb2.DroneEvent:
    return await asyncio.wait_for(next_message(stream), 5)


async def stream_ended(
    stream: grpc.aio.UnaryStreamCall[drone_pb2.ConnectRequest, drone_pb2.DroneEvent],
) -> bool:
    """Whether the stream ends (within 5 s) with no further event."""
    read = read_message(stream)
    return await asyncio.wait_for(read, 5) is None


async def test_connect_only_for_the_master(drone: DroneUnderTest) -> None:
    error = await expect_error(
        drone.stub.Connect(drone_pb2.ConnectRequest(controller_id=1)).read(),
        grpc.StatusCode.FAILED_PRECONDITION,
    )
    assert trailing(error)["baton-master"] == "0"
    await expect_error(
        drone.stub.Connect(drone_pb2.ConnectRequest(controller_id=9)).read(),
        grpc.StatusCode.INVALID_ARGUMENT,
    )


async def test_handover_rpc_notifies_the_connected_master(drone: DroneUnderTest) -> None:
    stream = drone.stub.Connect(drone_pb2.ConnectRequest(controller_id=0))
    event = await next_event(stream)
    assert event.connected == drone_pb2.Connected(master=0, last_reqnr=0, epoch=1)
    assert (await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())).master_connected
    await drone.stub.Invoke(invoke(0, 1, POSITION))
    reply = await drone.stub.Handover(drone_pb2.HandoverRequest(new_master=2))
    assert reply == drone_pb2.HandoverReply(old_master=0, new_master=2, after_reqnr=1, epoch=2)
    event = await next_event(stream)
    assert event.handover == drone_pb2.HandoverNotice(
        old_master=0, new_master=2, after_reqnr=1, ended_epoch=1, epoch=2
    )
    assert await stream_ended(stream)
    await expect_error(
        drone.stub.Invoke(invoke(0, 2, POSITION)), grpc.StatusCode.FAILED_PRECONDITION
    )
    await drone.stub.Invoke(invoke(2, 2, POSITION, epoch=2))
    status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
    record = status.handovers[0]
    assert (record.old_master, record.new_master, record.after_reqnr, record.trigger) == (
        0,
        2,
        1,
        drone_pb2.HANDOVER_TRIGGER_RPC,
    )
    assert record.first_request_at >= record.decided_at > 0
    assert record.delay_s == pytest.approx(record.first_request_at - record.decided_at)


async def test_handover_rpc_bad_targets(drone: DroneUnderTest) -> None:
    await expect_error(
        drone.stub.Handover(drone_pb2.HandoverRequest(new_master=7)),
        grpc.StatusCode.INVALID_ARGUMENT,
    )
    await expect_error(
        drone.stub.Handover(drone_pb2.HandoverRequest(new_master=0)),
        grpc.StatusCode.FAILED_PRECONDITION,
    )


async def test_scripted_handover_after_the_right_request() -> None:
    drone, server = await start_drone(script="# after 2 to 1\n2 1\n")
    try:
        stream = drone.stub.Connect(drone_pb2.ConnectRequest(controller_id=0))
        assert (await next_event(stream)).HasField("connected")
        await drone.stub.Invoke(invoke(0, 1, POSITION))
        # The reply of the scripted request still goes to the old master.
        reply = await drone.stub.Invoke(invoke(0, 2, ARM))
        assert reply.reqnr == 2 and not reply.duplicate
        event = await next_event(stream)
        assert event.handover == drone_pb2.HandoverNotice(
            old_master=0, new_master=1, after_reqnr=2, ended_epoch=1, epoch=2
        )
        # The new master re-sends the request in flight at the handover: cached.
        again = await drone.stub.Invoke(invoke(1, 2, ARM, epoch=2))
        assert again.duplicate and drone.vehicle.calls.count("Arm") == 1
        status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        assert (
            status.master == 1 and status.handovers[0].trigger == drone_pb2.HANDOVER_TRIGGER_SCRIPT
        )
        assert status.handovers[0].delay_s > 0
    finally:
        await server.stop(0)


async def test_notice_waits_for_a_disconnected_old_master(drone: DroneUnderTest) -> None:
    """The old master connected once (it is ACTIVE and holds the log: a cooperative
    handover), then its stream went; the notice waits for its next Connect. (A Handover
    before the initial master ever connected is a takeover: finding F1's narrowing.)"""
    first = drone.stub.Connect(drone_pb2.ConnectRequest(controller_id=0))
    assert (await next_event(first)).HasField("connected")
    first.cancel()

    async def stream_gone() -> bool:
        status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        return not status.master_connected

    await eventually(stream_gone, "the drone seeing the old master's stream gone")
    await drone.stub.Handover(drone_pb2.HandoverRequest(new_master=1))
    status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
    assert status.handovers[-1].kind == drone_pb2.HANDOVER_KIND_COOPERATIVE
    stream = drone.stub.Connect(drone_pb2.ConnectRequest(controller_id=0, mastership_epoch=1))
    event = await next_event(stream)
    assert event.handover == drone_pb2.HandoverNotice(
        old_master=0, new_master=1, after_reqnr=0, ended_epoch=1, epoch=2
    )
    assert await stream_ended(stream)
    # Delivered once: the next Connect of the old master is refused.
    await expect_error(
        drone.stub.Connect(drone_pb2.ConnectRequest(controller_id=0)).read(),
        grpc.StatusCode.FAILED_PRECONDITION,
    )


async def test_reconnect_supersedes_the_old_stream(drone: DroneUnderTest) -> None:
    first = drone.stub.Connect(drone_pb2.ConnectRequest(controller_id=0))
    assert (await next_event(first)).HasField("connected")
    second = drone.stub.Connect(drone_pb2.ConnectRequest(controller_id=0))
    assert (await next_event(second)).HasField("connected")
    assert await stream_ended(first)
    await drone.stub.Handover(drone_pb2.HandoverRequest(new_master=1))
    assert (await next_event(second)).HasField("handover")


async def test_handover_waits_for_the_request_being_served(drone: DroneUnderTest) -> None:
    gate = asyncio.Event()
    original = drone.vehicle.Arm

    async def slow_arm(request: api.ArmRequest) -> api.ArmReply:
        await gate.wait()
        return await original(request)

    drone.vehicle.Arm = slow_arm  # type: ignore[method-assign]
    arm = asyncio.ensure_future(drone.stub.Invoke(invoke(0, 1, ARM)))
    deadline = asyncio.get_running_loop().time() + 5
    while not drone.service._lock.locked():
        assert asyncio.get_running_loop().time() < deadline, "Arm never started"
        await asyncio.sleep(0.01)
    handover = asyncio.ensure_future(drone.stub.Handover(drone_pb2.HandoverRequest(new_master=1)))
    # The barrier: the Handover RPC has reached the drone and is queued on the lock
    # the Arm holds. Only the gate releases it from there, so it cannot be done yet.
    await eventually(lambda: drone.service._lock._waiters, "the handover queued on the lock")
    assert not handover.done()
    assert drone.service.seq.master == 0, "no switch while the request is served"
    gate.set()
    assert (await arm).reqnr == 1
    assert (await handover).after_reqnr == 1


async def test_a_call_the_caller_gave_up_on_is_executed_once_and_recorded(
    drone: DroneUnderTest,
) -> None:
    """Issue 9, defect 1: the caller's deadline must not cancel what the vehicle does."""
    drone.vehicle.gate = asyncio.Event()
    goto = invoke(0, 1, GOTO, api.GotoRequest(latitude_deg=47.4, longitude_deg=8.5))
    await expect_error(drone.stub.Invoke(goto, timeout=0.3), grpc.StatusCode.DEADLINE_EXCEEDED)
    assert drone.vehicle.calls == ["Goto"]  # it reached the vehicle, which is still at it
    drone.vehicle.gate.set()
    await eventually(lambda: drone.service.last_reqnr == 1, "the request recorded")
    again = await drone.stub.Invoke(goto)
    assert again.duplicate and drone.vehicle.calls == ["Goto"]
    assert [a.reqnr for a in drone.service.audit] == [1]


async def test_a_duplicate_while_the_original_executes_waits_for_its_outcome(
    drone: DroneUnderTest,
) -> None:
    drone.vehicle.gate = asyncio.Event()
    goto = invoke(0, 1, GOTO, api.GotoRequest(latitude_deg=47.4, longitude_deg=8.5))
    first = asyncio.ensure_future(drone.stub.Invoke(goto))
    await eventually(lambda: drone.vehicle.calls == ["Goto"], "the original executing")
    second = asyncio.ensure_future(drone.stub.Invoke(goto))
    drone.vehicle.gate.set()
    replies = await asyncio.gather(first, second)
    assert sorted(r.duplicate for r in replies) == [False, True]
    assert drone.vehicle.calls == ["Goto"]


async def test_a_failure_that_executed_nothing_leaves_the_reqnr_unused(
    drone: DroneUnderTest,
) -> None:
    """Issue 9, defect 2: "vehicle not connected" is not the request's outcome."""
    drone.vehicle.is_connected = False
    takeoff = invoke(0, 1, ARM)
    error = await expect_error(drone.stub.Invoke(takeoff), grpc.StatusCode.UNAVAILABLE)
    assert "not connected" in (error.details() or "")
    assert drone.service.last_reqnr == 0 and not drone.service.audit
    drone.vehicle.is_connected = True  # the link is back: the same reqnr executes now
    reply = await drone.stub.Invoke(takeoff)
    assert not reply.duplicate and drone.vehicle.calls == ["Arm"]
    assert drone.service.last_reqnr == 1
