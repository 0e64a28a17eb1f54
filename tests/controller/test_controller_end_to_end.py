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
from pathlib import Path

import pytest

# Re-exported for tests/controller/test_takeover.py, which imports them from here.
from helpers.missions import FAST_LINK, SMALL_GRID, assert_mission_promises, fly

from baton.testbed.local import LocalTestbed, TestbedPlan, local_config


@pytest.mark.parametrize(
    ("flush_limit", "forwarding"),
    [
        (0, "cut-through"),
        # On demand (~21 s; CI's 25 minutes): the paper's mode flies six controllers in CI
        # (test_forwarding_end_to_end.py).
        pytest.param(2 * 2**20, "store-and-forward", marks=pytest.mark.slow),
    ],
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
    # The restarted one greeted with what its file held (the last it handled before
    # the stop, which under load may lag the drone's request 14 by a message or two).
    assert ups[-1]["lognr"] >= 14 and ups[-1]["peer_lognr"] > 0
    assert '"recovered from the log file"' in (tmp_path / "logs" / "controller-2.log").read_text()
