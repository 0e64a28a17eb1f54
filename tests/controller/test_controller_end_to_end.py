"""Whole missions across real processes: sim vehicle, drone, links, controllers, programs.

Each run flies a small grid (high speed-up) with scripted handovers and then
checks the paper's promises against the drone's own audit: every request
executed exactly once, every waypoint photographed once, every replica saw
the same replies, and every scripted handover happened. Exactly once is also
checked where the side effects happened, trusting no part of baton's
bookkeeping: the pictures the camera produced and the commands the sim
vehicle acted on (``baton.testbed.report.check_side_effects``).
"""

from __future__ import annotations

import asyncio
import json
from collections import Counter
from pathlib import Path

import pytest

from baton.config import LinkSpec
from baton.testbed.local import LocalTestbed, MissionPlan, Snapshot, TestbedPlan, local_config
from baton.testbed.report import NOT_COUNTED, check_side_effects
from baton.v1 import drone_pb2, ring_pb2

SMALL_GRID = MissionPlan(grid=2, spacing_m=20.0, altitude_m=5.0, speed_m_s=5.0, poll_s=1.0)
FAST_LINK = LinkSpec(latency=0.002, bandwidth=None)


def assert_mission_promises(snapshot: Snapshot, plan: TestbedPlan) -> None:
    drone = snapshot.drone
    waypoints = plan.mission.grid**2
    for cid, c in snapshot.controllers.items():
        assert c.mission == ring_pb2.MISSION_STATE_DONE, (
            f"controller {cid}: mission {c.mission}: {c.mission_error}"
        )
    # Every request number executed exactly once, in order; every drone call
    # the replicas' programs made is in the audit (Clock calls are logged by
    # the controllers and never reach the drone, hence gaps in the numbers).
    executed = [a.reqnr for a in drone.audit]
    assert executed == sorted(set(executed))
    assert drone.executed == len(executed)
    assert {c.drone_calls for c in snapshot.controllers.values()} == {len(executed)}
    # Every waypoint photographed once.
    assert snapshot.pictures == waypoints
    # The same, counted where it happened: one picture per waypoint produced
    # by the camera; one arm, takeoff and land, and each goto once and in the
    # grid's order, acted on by the sim vehicle (SITL or an autopilot of its
    # own counts nothing).
    effects = check_side_effects(snapshot, plan.mission.grid, plan.mission.spacing_m)
    assert effects["exactly_once"] is True, effects
    assert effects["pictures_taken"] == waypoints, effects
    if plan.vehicle == "sim":
        assert effects["vehicle_commands"]["goto"] == waypoints, effects
    else:
        assert effects["vehicle_commands"] == NOT_COUNTED, effects
    # Every replica's program saw the same replies, and as many as the drone served.
    chains = Counter(c.reply_chain for c in snapshot.controllers.values())
    assert len(chains) == 1, f"replicas diverged: {chains}"
    assert len({c.reqnr for c in snapshot.controllers.values()}) == 1
    # Every scripted handover happened after the right request, and ended.
    # (A scripted reqnr that was a Clock call fires after the next drone request.)
    scripted = [h for h in drone.handovers if h.trigger == drone_pb2.HANDOVER_TRIGGER_SCRIPT]
    assert [h.new_master for h in scripted] == [mid for _, mid in plan.handovers]
    for record, (planned, _) in zip(scripted, plan.handovers, strict=True):
        # A prepared handover moves the master once the target caught up, later.
        assert planned <= record.after_reqnr <= planned + (1000 if plan.prepared else 2)
    # Every handover ended with the new master's first request, except one whose old
    # master's log never left (it died, or it was out of reach): the next record takes
    # the new master's role over, re-granting it or giving it to another.
    records = list(drone.handovers)
    for i, record in enumerate(records):
        after = records[i + 1] if i + 1 < len(records) else None
        taken_over = (
            after is not None
            and after.kind == drone_pb2.HANDOVER_KIND_TAKEOVER
            and record.new_master in (after.new_master, after.old_master)
        )
        assert record.delay_s > 0 or taken_over
    assert [c.master for c in snapshot.controllers.values()].count(True) == 1


async def fly(tmp_path: Path, plan: TestbedPlan, timeout: float = 240) -> Snapshot:
    async with LocalTestbed(plan, tmp_path) as testbed:
        snapshot = await testbed.run_mission(timeout)
    assert_mission_promises(snapshot, plan)
    return snapshot


@pytest.mark.parametrize(
    ("flush_limit", "forwarding"),
    [(0, "cut-through"), (2 * 2**20, "store-and-forward")],
    ids=["flush-0", "flush-2MB-paper"],
)
async def test_two_controllers_three_handovers(
    tmp_path: Path, flush_limit: int, forwarding: str
) -> None:
    plan = TestbedPlan(
        config=local_config(
            2,
            flush_limit=flush_limit,
            ring={"forwarding": forwarding},
            speedup=20.0,
            controller_link=FAST_LINK,
            drone_link=FAST_LINK,
        ),
        handovers=((8, 1), (16, 0), (24, 1)),
        mission=SMALL_GRID,
    )
    snapshot = await fly(tmp_path, plan)
    assert snapshot.drone.master == 1
    # Each new master connected on a channel to the drone connected in advance (TCP
    # and HTTP/2 made long before the handover), each controller's first one not.
    connecting = [
        json.loads(line)["connected_in_advance"]
        for cid in (0, 1)
        for line in (tmp_path / "logs" / f"controller-{cid}.log").read_text().splitlines()
        if '"connecting to the drone"' in line
    ]
    assert sorted(connecting) == [False, False, True, True, True], connecting


async def test_six_controllers_handovers_over_one_three_and_five_hops(tmp_path: Path) -> None:
    plan = TestbedPlan(
        config=local_config(
            6, flush_limit=0, speedup=20.0, controller_link=FAST_LINK, drone_link=FAST_LINK
        ),
        handovers=((6, 1), (12, 4), (18, 3)),  # 0->1: 1 hop, 1->4: 3 hops, 4->3: 5 hops
        mission=SMALL_GRID,
    )
    snapshot = await fly(tmp_path, plan)
    assert snapshot.drone.master == 3


@pytest.mark.parametrize("order", ["notice-first", "reply-first"])
async def test_handover_while_a_call_is_in_flight_both_orders(tmp_path: Path, order: str) -> None:
    """Footnote 2, forced: the drone holds back the reply (or the notice) at every handover."""
    plan = TestbedPlan(
        config=local_config(
            2, flush_limit=0, speedup=20.0, controller_link=FAST_LINK, drone_link=FAST_LINK
        ),
        handovers=((8, 1), (16, 0), (24, 1)),
        mission=SMALL_GRID,
        drone_args=("--force-race", order, "--race-delay", "0.3"),
    )
    snapshot = await fly(tmp_path, plan)
    old_master_logs = "".join(
        (tmp_path / "logs" / f"controller-{cid}.log").read_text() for cid in (0, 1)
    )
    discarded = old_master_logs.count("reply discarded after handover")
    if order == "notice-first":
        # Each old master dropped its in-flight reply; each new master re-sent
        # that request and the drone answered it from its cache.
        assert discarded == 3
        assert snapshot.drone.duplicates == 3
    else:
        assert discarded == 0
        assert snapshot.drone.duplicates == 0


async def test_a_replica_that_restarts_catches_up_from_its_predecessor(tmp_path: Path) -> None:
    """A controller stopped mid-mission and restarted recovers its log file, and its
    predecessor gives it the rest."""
    plan = TestbedPlan(
        config=local_config(
            3, flush_limit=0, speedup=20.0, controller_link=FAST_LINK, drone_link=FAST_LINK
        ),
        handovers=((8, 1), (30, 0)),
        mission=SMALL_GRID,
    )
    async with LocalTestbed(plan, tmp_path) as testbed:
        deadline = asyncio.get_running_loop().time() + 120
        while (await testbed.snapshot(audit=False)).drone.last_reqnr < 14:
            assert asyncio.get_running_loop().time() < deadline, "mission did not start"
            await asyncio.sleep(0.05)
        part = testbed.supervisor.parts["controller-2"]
        await testbed.supervisor.stop_part("controller-2")
        assert part.ready_file is not None
        restarted = await testbed.supervisor.start("controller-2", part.argv, part.ready_file)
        await testbed.supervisor.wait_ready(restarted)
        snapshot = await testbed.run_mission(240)
    assert_mission_promises(snapshot, plan)
    # The predecessor's stream came up twice: to a controller holding nothing at
    # the start, and, mid-mission, to one that had recovered its log file.
    ups = [
        json.loads(line)
        for line in (tmp_path / "logs" / "controller-1.log").read_text().splitlines()
        if '"ring stream up"' in line and '"peer": 2' in line
    ]
    assert len(ups) >= 2 and ups[0]["peer_lognr"] == 0
    assert ups[-1]["lognr"] >= 14 and ups[-1]["peer_lognr"] >= 14
    assert '"recovered from the log file"' in (tmp_path / "logs" / "controller-2.log").read_text()
