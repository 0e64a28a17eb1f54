"""Issue 11 across real processes: identities come from certificates, and every attack
of the issue's list fails with the right status while the mission flies on exactly once."""

from __future__ import annotations

import asyncio
import shutil
from collections.abc import Awaitable
from datetime import UTC, datetime, timedelta
from pathlib import Path

import grpc
import pytest
from helpers.missions import assert_mission_promises, attacked_ring

from baton.certs.make import init, issue
from baton.rpc.channels import aio_channel, sync_channel
from baton.rpc.tls import DRONE, Identity, Tls
from baton.testbed.local import LocalTestbed
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2, drone_pb2_grpc, ring_pb2, ring_pb2_grpc


async def refusal(call: Awaitable[object]) -> grpc.aio.AioRpcError:
    """The error a call (awaitable) ended with; fails the test if it succeeded."""
    with pytest.raises(grpc.aio.AioRpcError) as refused:
        await call
    return refused.value


async def test_callers_are_who_their_certificates_say_and_attacks_change_nothing(
    tmp_path: Path,
) -> None:
    plan = attacked_ring()
    async with LocalTestbed(plan, tmp_path) as testbed:
        config = testbed.config
        assert config is not None and testbed.tls is not None
        deadline = asyncio.get_running_loop().time() + 120
        while (await testbed.snapshot(audit=False)).drone.last_reqnr < 5:
            assert asyncio.get_running_loop().time() < deadline, "mission did not start"
            await asyncio.sleep(0.05)
        certs = config.tls.certs
        replica = Tls.load(certs, Identity.controller(2))  # a controller, never master here
        position = api.GetPositionRequest().SerializeToString()

        async with aio_channel(config.drone.address, replica, DRONE) as channel:
            drone = drone_pb2_grpc.DroneStub(channel)
            # The master's id written in the request, with another controller's certificate.
            invoke = drone_pb2.InvokeRequest(
                controller_id=0, reqnr=2**64 - 1, method="/baton.v1.Mobility/Goto", epoch=1
            )
            denied = await refusal(drone.Invoke(invoke))
            assert denied.code() is grpc.StatusCode.PERMISSION_DENIED
            assert "spiffe://baton/controller/2" in (denied.details() or "")
            assert "controller_id 0" in (denied.details() or "")
            # The same on the kept stream a master sends its calls on: the call is refused.
            stream = drone.InvokeStream()
            await stream.write(drone_pb2.InvokeCall(call=1, request=invoke))
            outcome = await stream.read()
            assert isinstance(outcome, drone_pb2.InvokeOutcome) and outcome.call == 1
            assert outcome.failure.code == grpc.StatusCode.PERMISSION_DENIED.value[0]
            assert "controller_id 0" in outcome.failure.message
            stream.cancel()
            connect = drone.Connect(drone_pb2.ConnectRequest(controller_id=0))
            denied = await refusal(connect.read())
            assert denied.code() is grpc.StatusCode.PERMISSION_DENIED
            standby = drone.Standby(drone_pb2.StandbyRequest(controller_id=0))
            denied = await refusal(standby.read())
            assert denied.code() is grpc.StatusCode.PERMISSION_DENIED
            # Nor may it answer another's ping (the round trip the drone measures).
            denied = await refusal(drone.AnswerPing(drone_pb2.PingAnswer(controller_id=0, seq=1)))
            assert denied.code() is grpc.StatusCode.PERMISSION_DENIED
            # A controller cannot move the master; an operator can (below).
            denied = await refusal(drone.Handover(drone_pb2.HandoverRequest(new_master=2)))
            assert denied.code() is grpc.StatusCode.PERMISSION_DENIED
            assert "only an operator" in (denied.details() or "")
            # Nor give the mission the vehicle back after a failsafe (issue 32).
            denied = await refusal(drone.Resume(drone_pb2.ResumeRequest()))
            assert denied.code() is grpc.StatusCode.PERMISSION_DENIED
            assert "only an operator" in (denied.details() or "")
            # Its own id is fine for reading the status, which shows every controller's
            # round trip measured through mutual TLS and the link emulators.
            while not all(
                link.answers and link.healthy
                for link in (await drone.GetStatus(drone_pb2.GetDroneStatusRequest())).links
            ):
                assert asyncio.get_running_loop().time() < deadline, "links not measured"
                await asyncio.sleep(0.1)

        # No certificate, one of another CA, an expired one: the drone's port takes none.
        foreign = tmp_path / "foreign"
        init(foreign, [Identity.controller(0)])
        stolen = Tls.load(foreign, Identity.controller(0))
        expired = tmp_path / "expired"
        shutil.copytree(certs, expired)
        issue(expired, Identity.controller(0), days=1, not_before=datetime.now(UTC) - timedelta(2))
        for tls in (
            None,
            Tls(stolen.identity, replica.ca, stolen.cert, stolen.key),
            Tls.load(expired, Identity.controller(0)),
        ):
            async with aio_channel(config.drone.address, tls, DRONE) as channel:
                stub = drone_pb2_grpc.DroneStub(channel)
                failed = await refusal(stub.GetStatus(drone_pb2.GetDroneStatusRequest(), timeout=5))
                assert failed.code() is grpc.StatusCode.UNAVAILABLE

        # A forged log frame: from an operator (refused as the stream opens), and from a
        # controller naming another (refused at the frame).
        operator = testbed.tls
        frame = ring_pb2.LogFrame(from_id=0, lognr=10**6, data=position)
        for tls, message in (
            (operator, "LogRing: refused to spiffe://baton/operator: log frames come from the"),
            (replica, "controller 2's certificate sent a frame from_id 0"),
        ):
            forged = await asyncio.to_thread(
                forged_frame_refusal, config.controller(1).address, tls, frame
            )
            assert forged.code() is grpc.StatusCode.PERMISSION_DENIED, forged.details()
            assert message in (forged.details() or ""), forged.details()

        # The operator hands over to 2 and the mission flies on.
        async with aio_channel(config.drone.address, operator, DRONE) as channel:
            moved = await drone_pb2_grpc.DroneStub(channel).Handover(
                drone_pb2.HandoverRequest(new_master=2)
            )
            assert moved.new_master == 2
        snapshot = await testbed.run_mission(240)
    assert_mission_promises(snapshot, plan)
    assert snapshot.drone.master == 2
    assert not any(a.method.endswith("/Goto") and a.reqnr > 10**6 for a in snapshot.drone.audit)


def forged_frame_refusal(address: str, tls: Tls, frame: ring_pb2.LogFrame) -> grpc.Call:
    """Sends ``frame`` on a LogRing stream to ``address`` and returns the call the server
    ended (fails the test if it did not refuse).

    The blocking stub: its status is the server's, however the frame's write ends. The
    asyncio stub's is not: a server that refuses while the frame is still being written
    fails that write, and the asyncio stub then ends the call INTERNAL ("Internal error
    from Core", SendMessageOperation) in place of the server's status (a CI flake)."""
    with sync_channel(address, tls, Identity.controller(1)) as channel:
        replies = ring_pb2_grpc.ControllerRingStub(channel).LogRing(iter([frame]), timeout=30)
        with pytest.raises(grpc.RpcError) as refused:
            for _ in replies:
                pass
    assert isinstance(refused.value, grpc.Call)  # the blocking stub's error is its call
    return refused.value
