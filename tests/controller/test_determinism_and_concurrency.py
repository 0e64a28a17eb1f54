"""The determinism guard across real processes, and one call at a time."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import grpc
import pytest
from helpers.missions import FAST_LINK, SMALL_GRID, assert_mission_promises
from waiting import eventually

from baton.config import LinkSpec, parse_config
from baton.controller.node import ControllerNode
from baton.digest import request_digest
from baton.rpc.channels import aio_channel
from baton.rpc.errors import StatusError
from baton.rpc.tls import Identity
from baton.testbed.local import LocalTestbed, TestbedPlan, local_config
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_api_pb2_grpc, ring_pb2, ring_pb2_grpc

MISSIONS = Path(__file__).parent / "missions"


async def test_a_diverging_mission_is_stopped_with_both_requests_shown(tmp_path: Path) -> None:
    plan = TestbedPlan(
        config=local_config(2, flush_limit=0, speedup=20.0),
        emulate_links=False,
        mission_file=MISSIONS / "diverging.py",
    )
    async with LocalTestbed(plan, tmp_path) as testbed:
        snapshot = await testbed.run_mission(120)
    master, replica = snapshot.controllers[0], snapshot.controllers[1]
    assert master.mission == ring_pb2.MISSION_STATE_DONE
    assert replica.mission == ring_pb2.MISSION_STATE_FAILED
    error = replica.mission_error
    assert "non-deterministic mission program at request 2" in error
    # Both requests decoded as `baton replay` shows them, and the field that differs.
    assert error.count("Camera.SetResolution {width: ") == 2  # the logged one and this one
    assert "(fields that differ: width)" in error
    program_output = (tmp_path / "logs" / "controller-1.log").read_text()
    assert "DroneCallError: Camera.SetResolution failed with FAILED_PRECONDITION" in program_output
    # The drone executed the master's requests only, once each.
    assert [a.reqnr for a in snapshot.drone.audit] == [1, 2, 3]


async def gives_up_on_a_picture(mission: str, tmp_path: Path) -> dict[int, str]:
    """Runs ``mission``, which gives up on its first TakePicture while the drone is at it
    (0.3 s each way on the drone link), on two controllers; checks that the drone took
    both pictures, each once (the one given up reached the camera), and that the
    replica saw what the master's program saw. The controllers' logs, by id."""
    plan = TestbedPlan(
        config=local_config(
            2,
            flush_limit=0,
            speedup=20.0,
            drone_link=LinkSpec(latency=0.3, bandwidth=None),
            controller_link=LinkSpec(latency=0.002, bandwidth=None),
        ),
        mission_file=MISSIONS / mission,
    )
    async with LocalTestbed(plan, tmp_path) as testbed:
        snapshot = await testbed.run_mission(120)
    outputs = {}
    for cid, c in snapshot.controllers.items():
        assert c.mission == ring_pb2.MISSION_STATE_DONE, f"controller {cid}: {c.mission_error}"
        outputs[cid] = (tmp_path / "logs" / f"controller-{cid}.log").read_text()
    audit = [(a.reqnr, a.method.rsplit("/", 1)[1]) for a in snapshot.drone.audit]
    assert [m for _, m in audit].count("TakePicture") == 2, audit
    assert len({r for r, _ in audit}) == len(audit)
    chains = {c.reply_chain for c in snapshot.controllers.values()}
    assert len(chains) == 1, "the replica saw something else than the master's program"
    assert {c.drone_calls for c in snapshot.controllers.values()} == {len(audit)}
    return outputs


async def test_a_call_the_program_gave_up_on_is_logged_as_it_saw_it(tmp_path: Path) -> None:
    """Issue 9, defect 1, across processes: a TakePicture whose deadline (0.45 s) passed
    at the drone."""
    outputs = await gives_up_on_a_picture("gives_up.py", tmp_path)
    for output in outputs.values():
        assert "first picture: DEADLINE_EXCEEDED" in output, output


async def test_a_call_cancelled_on_the_programs_stream_is_logged_as_given_up(
    tmp_path: Path,
) -> None:
    """The SDK's calls travel on one kept stream (ring.proto ProgramCalls): a call the
    program cancels (after 0.45 s) must reach the master as a unary call's cancellation
    does, as the node's give-up, and the drone's side effect is counted once."""
    outputs = await gives_up_on_a_picture("cancels.py", tmp_path)
    assert "first picture: gave up" in outputs[0], outputs[0]
    # The replica's program got the master's give-up from the log (or gave up itself
    # while it waited for it): never the picture the master's program did not see.
    assert "first picture: reply" not in outputs[1], outputs[1]
    gave_up = [
        json.loads(line)
        for line in outputs[0].splitlines()
        if '"the mission program gave up on a call"' in line
    ]
    assert [(g["reqnr"], g["code"]) for g in gave_up] == [(2, "CANCELLED")], gave_up


async def test_an_outsider_calling_the_masters_proxy_is_refused_and_changes_nothing(
    tmp_path: Path,
) -> None:
    """Issue 9, defect 6: only the mission program may call a controller's drone API."""
    plan = TestbedPlan(
        config=local_config(
            2, flush_limit=0, speedup=20.0, controller_link=FAST_LINK, drone_link=FAST_LINK
        ),
        handovers=((10, 1),),
        mission=SMALL_GRID,
    )
    async with LocalTestbed(plan, tmp_path) as testbed:
        assert testbed.config is not None
        deadline = asyncio.get_running_loop().time() + 120
        while (await testbed.snapshot(audit=False)).drone.last_reqnr < 5:
            assert asyncio.get_running_loop().time() < deadline, "mission did not start"
            await asyncio.sleep(0.05)
        # The drone API is served on the mission program's loopback port only.
        status = (await testbed.snapshot(audit=False)).controllers[0]
        assert status.mission_address.startswith("127.0.0.1:")
        async with aio_channel(status.mission_address) as channel:
            mobility = drone_api_pb2_grpc.MobilityStub(channel)
            for _ in range(20):  # a monitoring tool on the master's node polling it
                with pytest.raises(grpc.aio.AioRpcError) as refused:
                    await mobility.GetHome(api.GetHomeRequest())
                assert refused.value.code() == grpc.StatusCode.PERMISSION_DENIED
                assert "mission program only" in (refused.value.details() or "")
            ring = ring_pb2_grpc.ControllerRingStub(channel)
            with pytest.raises(grpc.aio.AioRpcError) as refused:
                await ring.MissionDone(ring_pb2.MissionDoneRequest(failed=True, error="forged"))
            assert refused.value.code() == grpc.StatusCode.PERMISSION_DENIED
            status = await ring.GetStatus(ring_pb2.GetControllerStatusRequest())  # open
            assert status.mission == ring_pb2.MISSION_STATE_RUNNING
        # On the ring port, even an operator's certificate reaches no drone API.
        ring_port = testbed.config.controller(0).address
        async with aio_channel(ring_port, testbed.tls, Identity.controller(0)) as channel:
            with pytest.raises(grpc.aio.AioRpcError) as refused:
                await drone_api_pb2_grpc.MobilityStub(channel).GetHome(api.GetHomeRequest())
            assert refused.value.code() == grpc.StatusCode.UNIMPLEMENTED
        snapshot = await testbed.run_mission(240)
    assert_mission_promises(snapshot, plan)
    assert not any(a.method.endswith("/GetHome") for a in snapshot.drone.audit)


async def test_the_controller_refuses_a_second_concurrent_call() -> None:
    config = parse_config(
        {"controllers": [{"id": 0, "address": "127.0.0.1:1"}, {"id": 1, "address": "127.0.0.1:2"}]}
    )
    node = ControllerNode(config, 1)  # PASSIVE: its first call is held
    held = asyncio.create_task(node.program.call("/baton.v1.Mobility/GetPosition", b""))
    await asyncio.sleep(0)  # let the first call reach its wait
    with pytest.raises(StatusError) as refused:
        await node.program.call("/baton.v1.Mobility/GetHome", b"")
    assert refused.value.code is grpc.StatusCode.FAILED_PRECONDITION
    assert "concurrent call /baton.v1.Mobility/GetHome" in refused.value.message
    held.cancel()


async def test_a_call_that_overtakes_the_give_up_of_the_pending_one_waits_for_it() -> None:
    """The program gave up on a call (a deadline, a cancelled stream) and made its next
    one at once: the next one can reach the controller before the give-up does (another
    stream, or another connection). Found under load by the give-up tests: the next
    call was refused as concurrent and the mission failed."""
    config = parse_config(
        {"controllers": [{"id": 0, "address": "127.0.0.1:1"}, {"id": 1, "address": "127.0.0.1:2"}]}
    )
    node = ControllerNode(config, 1)  # PASSIVE: its calls are held until the log comes
    position, home = "/baton.v1.Mobility/GetPosition", "/baton.v1.Mobility/GetHome"
    held = asyncio.create_task(node.program.call(position, b""))
    await eventually(lambda: node.program.busy == position, "the first call held")
    second = asyncio.create_task(node.program.call(home, b""))
    # The barrier: the next call is in, waiting for the pending one to end, before
    # the give-up.
    await eventually(lambda: node.program.idle._waiters, "the next call waiting for the first")
    held.cancel()
    with pytest.raises(asyncio.CancelledError):
        await held
    await eventually(lambda: node.program.busy == home, "the next call held in its turn")
    assert not second.done()
    second.cancel()
    await node.stop()


async def test_calls_a_replicas_program_gave_up_on_take_their_own_log_entries() -> None:
    """A replica's program that gives up twice while the replica waits for the log: its
    next call gets the third entry, not the first (the master's program gave up too)."""
    config = parse_config(
        {"controllers": [{"id": 0, "address": "127.0.0.1:1"}, {"id": 1, "address": "127.0.0.1:2"}]}
    )
    node = ControllerNode(config, 1)  # PASSIVE: its calls are held until the log comes
    position, home = "/baton.v1.Mobility/GetPosition", "/baton.v1.Mobility/GetHome"
    for method in (position, home):
        held = asyncio.create_task(node.program.call(method, b""))
        await eventually(lambda m=method: node.program.busy == m, "the call held for the log")
        held.cancel()
        with pytest.raises(asyncio.CancelledError):
            await held
    third = asyncio.create_task(node.program.call(position, b""))
    await eventually(lambda: node.program.busy == position, "the third call held")
    cancelled = grpc.StatusCode.CANCELLED.value[0]
    entries = [
        ring_pb2.LogEntry(
            reqnr=k, method=m, request_digest=request_digest(m, b""), status_code=code, reply=r
        )
        for k, m, code, r in (
            (1, position, cancelled, b""),
            (2, home, cancelled, b""),
            (3, position, 0, b"third"),
        )
    ]
    await node.on_log(ring_pb2.LogMessage(lognr=1, origin=0, entries=entries))
    entry = await asyncio.wait_for(third, 5)
    assert entry.reqnr == 3 and entry.reply == b"third"
    assert node.protocol.reqnr == 3 and node.program.mission != ring_pb2.MISSION_STATE_FAILED
    await node.stop()


async def test_a_replicas_program_that_gave_up_waiting_for_the_log_starts_again(
    tmp_path: Path,
) -> None:
    """A replica whose program's deadline passed while it waited for the log (the master's
    program had its replies) restarts the program to replay the log, instead of stopping
    the mission on that replica with a determinism error."""
    plan = TestbedPlan(
        config=local_config(
            3,
            flush_limit=1 << 20,  # the log reaches the replicas at the end only
            speedup=20.0,
        ),
        emulate_links=False,
        mission_file=MISSIONS / "gives_up_on_replicas.py",
    )
    async with LocalTestbed(plan, tmp_path) as testbed:
        snapshot = await testbed.run_mission(120)
    for cid, c in snapshot.controllers.items():
        assert c.mission == ring_pb2.MISSION_STATE_DONE, f"controller {cid}: {c.mission_error}"
    master = (tmp_path / "logs" / "controller-0.log").read_text()
    assert all(f"position {k}: reply" in master for k in range(3)), master
    for cid in (1, 2):
        assert snapshot.controllers[cid].program_restarts >= 1
        output = (tmp_path / "logs" / f"controller-{cid}.log").read_text()
        assert "position 0: DEADLINE_EXCEEDED" in output  # the first run gave up ...
        assert "it starts again and replays the log" in output
        assert "position 2: reply" in output  # ... the restarted one replayed the replies
    assert snapshot.controllers[0].program_restarts == 0
    chains = {c.reply_chain for c in snapshot.controllers.values()}
    assert len(chains) == 1, "a replica's program saw something else than the master's"
    audit = [a.reqnr for a in snapshot.drone.audit]
    assert audit == [1, 2, 3, 4]  # each request executed once, by the master
