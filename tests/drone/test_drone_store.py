"""A restarted drone service resumes from its state file (issue 9, defect 10).

In-process drone services over real gRPC channels, one after the other on
the same SQLite file; the end-to-end kill -9 mid-mission is in
``tests/controller/test_faults_mid_mission.py``.
"""

from __future__ import annotations

import asyncio
import sqlite3
from pathlib import Path

import grpc
import pytest
from drone_harness import DroneUnderTest, connect_as_master, start_drone
from helpers.drone_calls import ARM, GOTO, POSITION, TAKEOFF, expect_error, invoke
from waiting import eventually

from baton.digest import request_digest
from baton.drone.safety import Failsafe
from baton.drone.sequencer import AUDIT_IN_MEMORY
from baton.drone.store import Counters, DroneStore, Intent, PolicyMemory
from baton.rpc.server import BatonServer
from baton.testbed.local import drone_status
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2

NOW = "/baton.v1.Clock/Now"
SCRIPT = "# after 2 to 1, after 5 to 2\n2 1\n5 2\n"


async def restart(
    previous: tuple[DroneUnderTest, BatonServer] | None, state: Path, script: str = SCRIPT
) -> tuple[DroneUnderTest, BatonServer]:
    """Stops the running drone (if any) and starts another on the same state file."""
    if previous is not None:
        drone, server = previous
        await server.stop(0)
        assert drone.service.store is not None
        drone.service.store.close()
    return await start_drone(script=script, state_file=str(state))


async def test_a_restarted_drone_resumes_master_requests_cache_audit_and_script(
    tmp_path: Path,
) -> None:
    state = tmp_path / "drone.sqlite"
    first = await restart(None, state)
    drone = first[0]
    await drone.stub.Invoke(invoke(0, 1, POSITION))
    await drone.stub.Invoke(invoke(0, 2, ARM))  # the script's line "2 1" fires
    await drone.stub.Invoke(invoke(1, 3, POSITION, epoch=2))
    second = await restart(first, state)
    drone = second[0]
    try:
        status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest(include_audit=True))
        assert status.master == 1 and status.last_reqnr == 3 and status.executed == 3
        assert [a.reqnr for a in status.audit] == [1, 2, 3]
        assert [(h.old_master, h.new_master, h.after_reqnr) for h in status.handovers] == [
            (0, 1, 2)
        ]
        assert status.handovers[0].delay_s > 0  # the new master's first request, kept too
        # The request in flight at the handover, re-sent by the new master: from the cache.
        again = await drone.stub.Invoke(invoke(1, 2, ARM, epoch=2))
        assert again.duplicate and "Arm" not in drone.vehicle.calls
        await expect_error(
            drone.stub.Invoke(invoke(0, 4, POSITION)), grpc.StatusCode.FAILED_PRECONDITION
        )
        # The script goes on from where it was: "2 1" is not fired again, "5 2" is.
        await drone.stub.Invoke(invoke(1, 4, POSITION, epoch=2))
        await drone.stub.Invoke(invoke(1, 5, POSITION, epoch=2))
        status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        assert status.master == 2 and len(status.handovers) == 2
    finally:
        await second[1].stop(0)


async def test_a_command_cut_off_by_a_restart_is_never_executed_again(tmp_path: Path) -> None:
    state = tmp_path / "drone.sqlite"
    first = await restart(None, state, script="")
    await first[0].stub.Invoke(invoke(0, 1, ARM))
    takeoff = invoke(0, 2, TAKEOFF, api.TakeoffRequest(altitude_m=10))
    # What a kill -9 leaves behind in the middle of request 2 (the store's own record).
    digest = request_digest(TAKEOFF, takeoff.payload)
    first[0].service.store.begin(Intent(2, TAKEOFF, digest, 0, 1.0))  # type: ignore[union-attr]
    second = await restart(first, state, script="")
    drone = second[0]
    try:
        error = await expect_error(drone.stub.Invoke(takeoff), grpc.StatusCode.UNKNOWN)
        assert "the vehicle may have acted" in (error.details() or "")
        assert "Takeoff" not in drone.vehicle.calls
        status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest(include_audit=True))
        assert [a.reqnr for a in status.audit] == [1, 2]
    finally:
        await second[1].stop(0)


async def test_a_read_cut_off_by_a_restart_is_executed_when_re_sent(tmp_path: Path) -> None:
    state = tmp_path / "drone.sqlite"
    store = DroneStore(state)
    store.close()
    first = await restart(None, state)
    first[0].service.store.begin(Intent(1, POSITION, b"d", 0, 1.0))  # type: ignore[union-attr]
    second = await restart(first, state)
    drone = second[0]
    try:
        reply = await drone.stub.Invoke(invoke(0, 1, POSITION))
        assert not reply.duplicate and drone.vehicle.calls.count("GetPosition") == 1
    finally:
        await second[1].stop(0)


def test_a_state_file_that_is_not_a_database_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "state.sqlite"
    bad.write_text("not a database\n" * 100)
    with pytest.raises(OSError, match=r"drone state file .*state\.sqlite \(--state\): file is not"):
        DroneStore(bad)


@pytest.mark.parametrize("durable", [True, False], ids=["state-file", "memory-only"])
async def test_the_audit_is_kept_in_bounded_memory_and_paged(tmp_path: Path, durable: bool) -> None:
    """Issue 9, defect 8: the audit grew for the whole mission and GetStatus sent all of it."""
    settings = {"state_file": str(tmp_path / "drone.sqlite")} if durable else {}
    drone, server = await start_drone(**settings)
    try:
        served = AUDIT_IN_MEMORY + 50
        for reqnr in range(1, served + 1):
            await drone.service.invoke(invoke(0, reqnr, POSITION), received_at=float(reqnr))
        assert len(drone.service.seq.audit) == AUDIT_IN_MEMORY  # the newest only
        status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        assert not status.audit and status.executed == served
        assert status.audit_oldest_reqnr == (1 if durable else 51)
        page = await drone.stub.GetStatus(
            drone_pb2.GetDroneStatusRequest(include_audit=True, audit_limit=400)
        )
        first = status.audit_oldest_reqnr
        assert [a.reqnr for a in page.audit] == list(range(first, first + 400))
        assert page.audit_more
        whole = await drone_status(drone.stub)  # every page, as the testbed reads it
        assert [a.reqnr for a in whole.audit] == list(range(first, served + 1))
        assert not whole.audit_more
    finally:
        await server.stop(0)
        if drone.service.store is not None:
            drone.service.store.close()


async def test_the_calls_a_master_answered_survive_a_drone_killed_executing_their_request(
    tmp_path: Path,
) -> None:
    """The master's Clock.Now came along with a Goto; the drone dies executing the Goto.
    Restarted, it still gives that time to a taker (with the Goto's cut-off outcome): it
    was kept with the request's intent, not with its outcome (the helper found it with
    the simulation, seed 1676, where the reading was lost)."""
    state = tmp_path / "drone.sqlite"
    first = await restart(None, state, script="")
    drone = first[0]
    await drone.stub.Invoke(invoke(0, 1, POSITION))
    now = api.NowReply(unix_time_s=1_700_000_012.5).SerializeToString()
    read = drone_pb2.RetainedReply(
        reqnr=2, method=NOW, request_digest=request_digest(NOW, b""), reply=now
    )
    goto = invoke(0, 3, GOTO, api.GotoRequest(latitude_deg=47.4, relative_altitude_m=10))
    goto.master_answers.append(read)
    drone.vehicle.gate = asyncio.Event()  # the Goto never finishes: the drone is killed
    pending = asyncio.ensure_future(drone.stub.Invoke(goto))
    await eventually(lambda: "Goto" in drone.vehicle.calls, "the Goto executing", 10)
    second = await restart(first, state, script="")
    pending.cancel()
    drone = second[0]
    try:
        await drone.stub.Handover(drone_pb2.HandoverRequest(new_master=1, takeover=True))
        connected, retained = await connect_as_master(drone.stub, 1, holds_reqnr=1)
        assert connected.retained_through == 3
        assert [r.reqnr for r in retained] == [1, 2, 3]  # 1 too: it is compared
        read.epoch = 1  # brought by the master of epoch 1
        assert retained[1] == read
        assert retained[2].status_code == grpc.StatusCode.UNKNOWN.value[0]
    finally:
        await second[1].stop(0)


async def test_a_restarted_drone_tells_a_taker_the_watermark_it_had(tmp_path: Path) -> None:
    """--policy nearest seed 201: the watermark was not kept, and a restarted drone said 0.
    The replies up to it were let go, so a taker restarted with nothing went ACTIVE at
    once (it held the 0 it was told it must) and waited for ever for request 1's reply.
    Kept with the counters, the taker is told it must hold up to 3 first, and is given
    only the replies above it."""
    state = tmp_path / "drone.sqlite"
    first = await restart(None, state, script="")
    drone = first[0]
    for reqnr in range(1, 6):
        request = invoke(0, reqnr, POSITION)
        request.watermark_reqnr = 3  # every controller holds up to request 3
        await drone.stub.Invoke(request)
    assert drone.service.seq.cache.watermark == 3
    second = await restart(first, state, script="")
    drone = second[0]
    try:
        assert drone.service.seq.cache.watermark == 3
        await drone.stub.Handover(drone_pb2.HandoverRequest(new_master=1, takeover=True))
        connected, retained = await connect_as_master(drone.stub, 1)
        assert connected.watermark_reqnr == 3
        assert [r.reqnr for r in retained] == [4, 5]
        assert [r.epoch for r in retained] == [1, 1]  # the mastership that brought each
        # The taker answered its program from both; its request 6 says so, and the
        # drone counts them as brought in its epoch 2, kept across a restart too.
        adopted = invoke(1, 6, POSITION, epoch=2)
        adopted.adopted_from_reqnr = 4
        await drone.stub.Invoke(adopted)
    finally:
        await second[1].stop(0)
    third = await restart(second, state, script="")
    try:
        kept = third[0].service.seq.cache
        assert [(r.reqnr, r.epoch) for r in kept.retained_replies()] == [(4, 2), (5, 2), (6, 2)]
    finally:
        await third[1].stop(0)


def test_a_state_file_from_before_the_watermark_was_kept_opens(tmp_path: Path) -> None:
    """A file written without the watermark column gets it (0: as that drone said), one
    without the replies' epochs gets them (0: older than any framing), and one without
    the policy's resumes gets them (0)."""
    state = tmp_path / "drone.sqlite"
    db = sqlite3.connect(state)
    db.execute(
        "CREATE TABLE state (id INTEGER PRIMARY KEY CHECK (id = 1), master INTEGER NOT NULL, "
        "last_reqnr INTEGER NOT NULL, executed INTEGER NOT NULL, duplicates INTEGER NOT NULL, "
        "rejected INTEGER NOT NULL, handovers BLOB NOT NULL, fired_script TEXT NOT NULL)"
    )
    db.execute("INSERT INTO state VALUES (1, 2, 7, 7, 0, 0, ?, '[]')", (b"",))
    db.execute(  # and without the replies' epochs
        "CREATE TABLE replies (reqnr INTEGER PRIMARY KEY, method TEXT NOT NULL, "
        "digest BLOB NOT NULL, reply BLOB NOT NULL, code INTEGER, message TEXT, metadata TEXT)"
    )
    db.execute("INSERT INTO replies VALUES (7, 'm', ?, ?, NULL, NULL, NULL)", (b"d", b"r"))
    db.execute(  # and without the policy's resumes
        "CREATE TABLE policy (id INTEGER PRIMARY KEY CHECK (id = 1), leg BLOB, "
        "held INTEGER NOT NULL)"
    )
    db.execute("INSERT INTO policy VALUES (1, NULL, 1)")
    db.commit()
    db.close()
    store = DroneStore(state)
    try:
        loaded = store.load()
        assert loaded is not None
        assert (loaded.counters.master, loaded.counters.last_reqnr) == (2, 7)
        assert loaded.counters.watermark == 0
        assert [(r.reqnr, r.epoch) for r in loaded.replies] == [(7, 0)]
        store.save(Counters(master=2, last_reqnr=8, watermark=5))
        loaded = store.load()
        assert loaded is not None and loaded.counters.watermark == 5
        assert store.load_policy() == PolicyMemory(None, True, 0)
        store.save_policy(PolicyMemory(None, False, 2))
        assert store.load_policy() == PolicyMemory(None, False, 2)
    finally:
        store.close()


async def test_the_cruise_speed_and_a_failsafe_survive_a_restart(tmp_path: Path) -> None:
    """Commanded state (issue 32, item 6): the mission's speed is given back to the vehicle
    backend, and a vehicle in failsafe stays there (requests refused, booked) until an
    operator's Resume."""
    state = tmp_path / "drone.sqlite"
    first = await restart(None, state, script="")
    drone = first[0]
    speed = api.SetSpeedRequest(speed_m_s=7.5)
    await drone.stub.Invoke(invoke(0, 1, "/baton.v1.Mobility/SetSpeed", speed))
    drone.service.core.enter_failsafe(Failsafe("lost_link", "rtl", 1.0, "no usable controller"))
    drone.service.save_failsafe()
    second = await restart(first, state, script="")
    drone = second[0]
    try:
        assert drone.vehicle.restored_speed == 7.5
        refused = await expect_error(
            drone.stub.Invoke(invoke(0, 2, POSITION)), grpc.StatusCode.FAILED_PRECONDITION
        )
        assert "in failsafe (lost_link" in (refused.details() or "")
        assert "GetPosition" not in drone.vehicle.calls  # nothing executed
        again = await expect_error(
            drone.stub.Invoke(invoke(0, 2, POSITION)), grpc.StatusCode.FAILED_PRECONDITION
        )
        assert again.details() == refused.details()  # booked: the same outcome again
        status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        assert status.failsafe.cause == "lost_link" and status.last_reqnr == 2
        await drone.stub.Resume(drone_pb2.ResumeRequest())
        await expect_error(
            drone.stub.Resume(drone_pb2.ResumeRequest()), grpc.StatusCode.FAILED_PRECONDITION
        )
        await drone.stub.Invoke(invoke(0, 3, POSITION))
        assert "GetPosition" in drone.vehicle.calls
    finally:
        await second[1].stop(0)
    third = await restart(second, state, script="")
    try:
        status = await third[0].stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        assert not status.HasField("failsafe")  # the resume is kept too
    finally:
        await third[1].stop(0)
