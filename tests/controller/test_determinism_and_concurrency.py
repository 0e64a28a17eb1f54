"""The determinism guard across real processes, and one call at a time."""

from __future__ import annotations

import asyncio
import threading
from pathlib import Path

import grpc
import pytest

from baton.config import LinkSpec, parse_config
from baton.controller.node import ControllerNode
from baton.rpc.errors import StatusError
from baton.sdk.drone import _Caller
from baton.sdk.errors import ConcurrentCallError
from baton.testbed.local import LocalTestbed, TestbedPlan

MISSIONS = Path(__file__).parent / "missions"


async def test_a_diverging_mission_is_stopped_with_both_requests_shown(tmp_path: Path) -> None:
    plan = TestbedPlan(
        controllers=2,
        flush_limit=0,
        speedup=20.0,
        emulate_links=False,
        mission_file=MISSIONS / "diverging.py",
    )
    async with LocalTestbed(plan, tmp_path) as testbed:
        snapshot = await testbed.run_mission(120)
    master, replica = snapshot.controllers[0], snapshot.controllers[1]
    assert master.mission == "done"
    assert replica.mission == "failed"
    error = replica.mission_error
    assert "non-deterministic mission program at request 2" in error
    assert error.count("/baton.v1.Camera/SetResolution") == 2  # the logged one and this one
    assert "request bytes" in error
    program_output = (tmp_path / "logs" / "controller-1.log").read_text()
    assert "DroneCallError: Camera.SetResolution failed with FAILED_PRECONDITION" in program_output
    # The drone executed the master's requests only, once each.
    assert [a.reqnr for a in snapshot.drone.audit] == [1, 2, 3]


async def test_a_call_the_program_gave_up_on_is_logged_as_it_saw_it(tmp_path: Path) -> None:
    """Issue 9, defect 1, across processes: a TakePicture whose deadline passed at the drone."""
    plan = TestbedPlan(
        controllers=2,
        flush_limit=0,
        speedup=20.0,
        mission_file=MISSIONS / "gives_up.py",
        # 0.3 s each way: the program's 0.45 s deadline passes while the drone is at it.
        drone_link=LinkSpec(latency=0.3, bandwidth=None),
        controller_link=LinkSpec(latency=0.002, bandwidth=None),
    )
    async with LocalTestbed(plan, tmp_path) as testbed:
        snapshot = await testbed.run_mission(120)
    for cid, c in snapshot.controllers.items():
        assert c.mission == "done", f"controller {cid}: {c.mission_error}"
        output = (tmp_path / "logs" / f"controller-{cid}.log").read_text()
        assert "first picture: DEADLINE_EXCEEDED" in output, output
    # The drone took both pictures, each once: the one the program gave up on
    # (it reached the camera) and the one it asked for again.
    audit = [(a.reqnr, a.method.rsplit("/", 1)[1]) for a in snapshot.drone.audit]
    assert [m for _, m in audit].count("TakePicture") == 2, audit
    assert len({r for r, _ in audit}) == len(audit)
    chains = {c.reply_chain for c in snapshot.controllers.values()}
    assert len(chains) == 1, "the replica saw something else than the master's program"
    assert {c.drone_calls for c in snapshot.controllers.values()} == {len(audit)}


async def test_the_controller_refuses_a_second_concurrent_call() -> None:
    config = parse_config(
        {"controllers": [{"id": 0, "address": "127.0.0.1:1"}, {"id": 1, "address": "127.0.0.1:2"}]}
    )
    node = ControllerNode(config, 1)  # PASSIVE: its first call is held
    held = asyncio.create_task(node.call("/baton.v1.Mobility/GetPosition", b""))
    await asyncio.sleep(0)  # let the first call reach its wait
    with pytest.raises(StatusError) as refused:
        await node.call("/baton.v1.Mobility/GetHome", b"")
    assert refused.value.code is grpc.StatusCode.FAILED_PRECONDITION
    assert "concurrent call /baton.v1.Mobility/GetHome" in refused.value.message
    held.cancel()


def test_the_sdk_refuses_a_second_concurrent_call() -> None:
    caller = _Caller()
    entered, release = threading.Event(), threading.Event()

    def slow(request: object, wait_for_ready: bool) -> str:
        entered.set()
        release.wait(10)
        return "reply"

    worker = threading.Thread(target=caller, args=("Mobility.GetPosition", slow, None))
    worker.start()
    assert entered.wait(10)
    with pytest.raises(ConcurrentCallError, match="one call at a time"):
        caller("Camera.TakePicture", slow, None)
    release.set()
    worker.join(10)
    assert caller("Mobility.GetPosition", lambda request, wait_for_ready: "ok", None) == "ok"
