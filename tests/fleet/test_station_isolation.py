"""Issue 34: one mission's stall touches no other mission on the stations they share,
measured at the other mission. Across real processes:
three `baton station`s, two missions (alpha on stations 1 and 2, bravo on 1 and 3),
each with its sim vehicle and drone service; station 1 is the master of both, and
every fault is alpha's, on station 1."""

from __future__ import annotations

import asyncio
import os
import signal
import time
from functools import partial
from pathlib import Path

from helpers.missions import SMALL_GRID, assert_mission_promises
from helpers.stations import program_pid, start_on_rings, stations_and_drones
from waiting import eventually

from baton.certs.make import init
from baton.rpc.channels import KEEPALIVE_MS, KEEPALIVE_TIMEOUT_MS
from baton.rpc.tls import DRONE, OPERATOR, Identity
from baton.testbed.fleet import MissionDrone, StationPart, mission_ended
from baton.testbed.local import TestbedPlan
from baton.testbed.supervisor import Supervisor

RINGS = {"alpha": (1, 2), "bravo": (1, 3)}
NO_HANDOVERS: dict[str, tuple[tuple[int, int], ...]] = {m: () for m in RINGS}
SHARED = 1  # the master of both missions, where alpha's faults are
GRIDS = {m: SMALL_GRID.args() for m in RINGS}
# A program stopped past the time a port gives a silent peer (a ping every 10 s, 5 s
# for its answer: rpc/channels.py), and a little more.
STALL_S = (KEEPALIVE_MS + KEEPALIVE_TIMEOUT_MS) / 1000 + 2.0


async def both_started(
    tmp_path: Path, supervisor: Supervisor
) -> tuple[Path, dict[int, StationPart], dict[str, MissionDrone]]:
    """Stations 1, 2 and 3, and each mission's vehicle and drone; the certificates."""
    certs = tmp_path / "certs"
    init(certs, [*(Identity.controller(s) for s in (1, 2, 3)), DRONE, OPERATOR])
    stations, drones = await stations_and_drones(supervisor, certs, RINGS, NO_HANDOVERS)
    return certs, stations, drones


async def close_all(stations: dict[int, StationPart], drones: dict[str, MissionDrone]) -> None:
    for channel in [
        *(s.channel for s in stations.values()),
        *(d.channel for d in drones.values()),
    ]:
        await channel.close()


async def test_a_stopped_program_stalls_its_own_mission_only(tmp_path: Path) -> None:
    async with Supervisor(tmp_path / "parts") as supervisor:
        certs, stations, drones = await both_started(tmp_path, supervisor)
        await start_on_rings(stations, drones, RINGS, certs, SMALL_GRID.file, GRIDS)
        for drone in drones.values():
            await eventually(partial(drone.served, 3), f"{drone.name} served request 3", 60)

        # alpha's program on station 1 stops (SIGSTOP) while both fly.
        stopped = await program_pid(supervisor, stations[SHARED], "alpha")
        os.kill(stopped, signal.SIGSTOP)
        stopped_at = time.monotonic()
        try:
            alpha_at = (await drones["alpha"].status()).last_reqnr
            bravo_at = (await drones["bravo"].status()).last_reqnr
            bravo = await eventually(
                lambda: mission_ended(stations, drones["bravo"], "bravo", RINGS["bravo"]),
                "bravo flown to its end while alpha's program is stopped",
                60,
            )
            served = {m: (await d.status()).last_reqnr for m, d in drones.items()}
            # alpha stood still (but for the call its program had in flight), bravo did not.
            assert served["alpha"] <= alpha_at + 1, (alpha_at, served)
            assert served["bravo"] > bravo_at + 20, (bravo_at, served)
            # The stall lasts past the time a port gives a silent peer: the program's
            # port must not take a stopped program for a dead one. This wait is the
            # fault's length, not a wait for an outcome.
            await asyncio.sleep(max(0.0, STALL_S - (time.monotonic() - stopped_at)))
        finally:
            os.kill(stopped, signal.SIGCONT)

        alpha = await eventually(
            lambda: mission_ended(stations, drones["alpha"], "alpha", RINGS["alpha"]),
            "alpha flown to its end once its program went on",
            60,
        )
        for mission, statuses in (("alpha", alpha), ("bravo", bravo)):
            snapshot = await drones[mission].snapshot(statuses)
            assert_mission_promises(snapshot, TestbedPlan(mission=SMALL_GRID))
            assert list(snapshot.drone.handovers) == []  # no takeover either
        await close_all(stations, drones)
