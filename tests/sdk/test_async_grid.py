"""The grid mission written with the asyncio SDK (baton/missions/grid_async.py), flown on a
real local testbed through handovers, and its controllers' logs replayed with ``baton replay``."""

from __future__ import annotations

import asyncio
from pathlib import Path

from baton.missions import grid, grid_async
from baton.replay.replayer import replay_log
from baton.testbed.local import LocalTestbed, MissionPlan, TestbedPlan, local_config
from baton.testbed.report import build_report
from baton.v1 import ring_pb2

ARGS = ("grid=2", "spacing_m=20", "altitude_m=5")


async def test_the_async_grid_flies_through_handovers_exactly_once(tmp_path: Path) -> None:
    plan = TestbedPlan(
        config=local_config(3, flush_limit=0, speedup=20.0),
        handovers=((8, 1), (16, 2), (24, 0)),
        emulate_links=False,
        mission=MissionPlan(grid=2, spacing_m=20.0, altitude_m=5.0),  # what the report expects
        mission_file=Path(grid_async.__file__),
        mission_args=ARGS,
    )
    async with LocalTestbed(plan, tmp_path) as testbed:
        snapshot = await testbed.run_mission(240)
        assert testbed.config is not None
        report = build_report(testbed.config, snapshot, 2, 1.0, list(plan.handovers))
        logs = testbed.files()["controller_logs"]
    for cid, c in snapshot.controllers.items():
        assert c.mission == ring_pb2.MISSION_STATE_DONE, f"controller {cid}: {c.mission_error}"
    assert report["completed"] and report["exactly_once"] and report["replicas_consistent"]
    assert [h["to"] for h in report["handovers"]] == [1, 2, 0]
    assert report["handovers_missed"] == []
    effects = report["side_effects"]
    assert effects["exactly_once"] is True and effects["problems"] == [], effects
    assert effects["pictures_taken"] == effects["pictures_expected"] == 4
    assert effects["vehicle_commands"]["goto"] == len(grid.waypoints(2, 20.0))
    output = (tmp_path / "logs" / "controller-0.log").read_text()
    assert "waypoint 4 of 4" in output and "mission complete" in output
    # Every replica's durable log replays clean against the async program, offline;
    # the blocking grid, which makes the same calls, too.
    for cid, log in logs.items():
        for program in (grid_async.__file__, grid.__file__):
            # Blocking (it runs an async program in an event loop of its own): in a thread.
            outcome = await asyncio.to_thread(replay_log, Path(log), program, list(ARGS))
            assert outcome.clean, (cid, program, outcome.divergence)
            assert outcome.replayed == outcome.logged == snapshot.drone.last_reqnr
