"""Issue 34, "Done when": a station killed mid-run. Its missions are taken over by the
other stations of their rings, and a mission whose ring does not hold it does not
notice. Across real processes: three `baton station`s, two missions (alpha on
stations 1, 2, 3; bravo on 1 and 3, sharing both with alpha), each with its sim
vehicle and drone service; station 2 is killed (kill -9) while it is alpha's master."""

from __future__ import annotations

from functools import partial
from pathlib import Path

from helpers.missions import SMALL_GRID, assert_mission_promises
from helpers.stations import start_on_rings, stations_and_drones
from waiting import eventually

from baton.certs.make import init
from baton.rpc.tls import DRONE, OPERATOR, Identity
from baton.testbed.local import TestbedPlan
from baton.testbed.supervisor import Supervisor
from baton.v1 import drone_pb2, ring_pb2

RINGS = {"alpha": (1, 2, 3), "bravo": (1, 3)}
HANDOVERS = {"alpha": ((3, 2),), "bravo": ()}
KILLED = 2


async def test_a_station_killed_mid_run_its_missions_taken_over_the_others_unaware(
    tmp_path: Path,
) -> None:
    certs = tmp_path / "certs"
    init(certs, [*(Identity.controller(s) for s in (1, 2, 3)), DRONE, OPERATOR])
    async with Supervisor(tmp_path / "parts") as supervisor:
        stations, drones = await stations_and_drones(supervisor, certs, RINGS, HANDOVERS)
        grids = {m: SMALL_GRID.args() for m in RINGS}
        await start_on_rings(stations, drones, RINGS, certs, SMALL_GRID.file, grids)

        async def alpha_mastered_by_the_doomed() -> bool:
            status = await drones["alpha"].status()
            return status.master == KILLED and status.last_reqnr >= 8

        await eventually(alpha_mastered_by_the_doomed, "station 2 alpha's master, serving", 120)
        await eventually(partial(drones["bravo"].served, 8), "bravo served request 8", 60)
        await supervisor.kill(f"station-{KILLED}")

        live = {m: tuple(s for s in ring if s != KILLED) for m, ring in RINGS.items()}

        async def ended(mission: str) -> dict[int, ring_pb2.ControllerStatus] | None:
            statuses = {sid: await stations[sid].status(mission) for sid in live[mission]}
            done = all(s.mission == ring_pb2.MISSION_STATE_DONE for s in statuses.values())
            drone = await drones[mission].status()
            return statuses if done and drone.preparing_for < 0 else None

        snapshots = {}
        for mission in RINGS:
            statuses = await eventually(lambda m=mission: ended(m), f"{mission} done", 180)
            snapshots[mission] = snapshot = await drones[mission].snapshot(statuses)
            plan = TestbedPlan(mission=SMALL_GRID, handovers=HANDOVERS[mission])
            assert_mission_promises(snapshot, plan)

        # alpha: the drone took the dead master's role over, to a station that lives.
        lost = [
            h
            for h in snapshots["alpha"].drone.handovers
            if h.trigger == drone_pb2.HANDOVER_TRIGGER_LOST
        ]
        assert lost and lost[0].old_master == KILLED and lost[0].new_master in live["alpha"], [
            (h.after_reqnr, h.old_master, h.new_master, h.trigger) for h in lost
        ]
        # bravo, on two of the same station processes: no handover, no takeover, no error.
        assert list(snapshots["bravo"].drone.handovers) == []
        assert {s.mission_error for s in snapshots["bravo"].controllers.values()} == {""}
        for sid in live["alpha"]:
            part = supervisor.parts[f"station-{sid}"]
            assert part.process is not None and part.returncode is None
        for channel in [
            *(s.channel for s in stations.values()),
            *(d.channel for d in drones.values()),
        ]:
            await channel.close()
