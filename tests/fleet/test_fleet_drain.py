"""``baton fleet drain`` against real processes: two missions over three stations; the
station that is master of one of them is drained mid-mission. Its master moves away,
it leaves both rings, both missions complete exactly once with consistent replicas,
and it hosts nothing at the end. Listing and status show the missions as their
stations say, a silent station as such; bad drains get clear errors."""

from __future__ import annotations

import json
from functools import partial
from pathlib import Path

import pytest
from helpers.missions import assert_mission_promises
from helpers.stations import fleet_cli, network_file
from waiting import eventually

from baton.certs.make import init
from baton.config import Location, load_config
from baton.fleet.registry import Registry
from baton.fleet.routes import survey_route
from baton.fleet.stations import ring_config
from baton.rpc.tls import DRONE, OPERATOR, Identity
from baton.sdk import offset
from baton.sdk.types import Position
from baton.testbed.fleet import mission_ended, start_mission_drone, start_stations
from baton.testbed.local import MissionPlan, TestbedPlan
from baton.testbed.supervisor import Supervisor
from baton.v1 import drone_pb2, station_pb2

HOME = Position(47.397742, 8.545594)
# Three stations 300 m apart, each covering the other two and both missions' routes:
# every ring can do without any one of them.
PLACES = {
    sid: (p.latitude_deg, p.longitude_deg)
    for sid, p in ((1, HOME), (2, offset(HOME, 0, 300)), (3, offset(HOME, 0, 600)))
}
# alpha takes off at station 1 (its first master), bravo at station 3.
TAKE_OFF = {"alpha": HOME, "bravo": offset(HOME, 0, 600)}
# Legs long enough (20 s of mission time at 5x) for the drain to happen in flight.
PLAN = MissionPlan(grid=2, spacing_m=60.0, altitude_m=5.0, speed_m_s=5.0, poll_s=1.0)
SPEEDUP = 5.0


async def test_a_station_drained_mid_mission_hands_its_master_over_and_leaves_both_rings(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    certs = tmp_path / "certs"
    init(certs, [*(Identity.controller(s) for s in PLACES), DRONE, OPERATOR])
    db = tmp_path / "fleet.sqlite"
    registry = ["--registry", str(db)]
    async with Supervisor(tmp_path / "parts") as supervisor:
        stations = await start_stations(supervisor, tuple(PLACES), certs)
        network = network_file(
            tmp_path / "network.yaml",
            stations,
            PLACES,
            2000,
            certs,
            speedup=SPEEDUP,
            flush_limit=0,
        )
        status, out = await fleet_cli(
            capsys, "stations", "add", "--from-config", str(network), *registry
        )
        assert status == 0, out
        drones, rings = {}, {}
        for number, (name, home) in enumerate(TAKE_OFF.items(), start=1):
            route = survey_route(home, PLAN.targets())
            points = [f"{p.latitude_deg},{p.longitude_deg}" for p in route]
            status, out = await fleet_cli(
                capsys, "admit", "--drone", name, "--route", *points, *registry
            )
            assert status == 0 and f"mission {number} admitted" in out, out
            with Registry(db) as r:
                mission = r.mission(number)
            rings[name] = mission.ring
            config = ring_config(load_config(network), mission.ring, mission.first_master)
            at_home = config.drone.model_copy(
                update={
                    "address": "127.0.0.1:0",
                    "home": Location(
                        latitude_deg=home.latitude_deg, longitude_deg=home.longitude_deg
                    ),
                }
            )
            drones[name] = await start_mission_drone(
                supervisor, name, config.model_copy(update={"drone": at_home})
            )
        assert rings == {"alpha": (1, 2, 3), "bravo": (3, 2, 1)}
        for drone in drones.values():
            await eventually(drone.ready, f"{drone.name}'s vehicle ready to arm", 120)
        for number, drone in enumerate(drones.values(), start=1):
            status, out = await fleet_cli(
                capsys,
                "start",
                str(number),
                "--config",
                str(network),
                "--drone-address",
                drone.address,
                "--mission",
                str(PLAN.file),
                *(f"--mission-arg={arg}" for arg in PLAN.args()),
                *registry,
            )
            assert status == 0, out
        for drone in drones.values():
            await eventually(partial(drone.served, 3), f"{drone.name} served request 3", 60)

        # The listing asks the stations: alpha's master is station 1, bravo's 3.
        status, out = await fleet_cli(capsys, "missions", "--config", str(network), *registry)
        assert status == 0, out
        rows = {line.split()[1]: line.split() for line in out.splitlines()[1:3]}
        assert rows["alpha"][2:4] == ["running", "1"] and rows["alpha"][5] == "1,2,3", out
        assert rows["bravo"][2:4] == ["running", "3"] and rows["bravo"][5] == "3,2,1", out

        # Bad drains: an unknown station; then, further down, one that would break a ring.
        status, out = await fleet_cli(
            capsys, "drain", "nosuch", "--config", str(network), *registry
        )
        assert status == 2, out
        assert "station 'nosuch': no station by that name or id; the stations: controller-1" in out

        status, out = await fleet_cli(
            capsys, "drain", "controller-1", "--config", str(network), *registry
        )
        assert status == 0, out
        assert "mission 1: left its ring, its master handed over to station 2" in out
        assert "mission 2: left its ring\n" in out
        alpha = await drones["alpha"].status()
        assert alpha.master == 2
        # Mid-mission: the drone had more to serve after the master moved.
        assert alpha.flight_state.in_air
        assert await stations[1].stub.GetStation(station_pb2.GetStationRequest()) == (
            station_pb2.StationStatus(id=1, address=stations[1].address)
        )
        status, out = await fleet_cli(capsys, "status", "1", "--config", str(network), *registry)
        assert status == 0, out
        full = json.loads(out)
        assert (full["ring"], full["departed"]) == ([2, 3], [1])
        assert set(full["sessions"]) == {"2", "3"}
        assert full["sessions"]["2"]["master"] is True
        assert full["drone_status"]["master"] == 2

        # Each ring keeps two stations now: draining one more would leave one.
        status, out = await fleet_cli(capsys, "drain", "2", "--config", str(network), *registry)
        assert status == 1, out
        assert "mission 1: stays in its ring: its ring [2, 3] would keep 1 station" in out
        assert "controller-2 still serves" not in out and "station 2 still serves 2" in out
        status, out = await fleet_cli(capsys, "undrain", "2", *registry)
        assert status == 0, out
        status, out = await fleet_cli(capsys, "stations", "list", *registry)
        assert [line.split()[-1] for line in out.splitlines()[1:]] == [
            "drained",
            "service",
            "service",
        ]

        live = {"alpha": (2, 3), "bravo": (3, 2)}
        for number, (name, ring) in enumerate(live.items(), start=1):
            drone = drones[name]
            statuses = await eventually(
                partial(mission_ended, stations, drone, str(number), ring), f"{name} ended", 120
            )
            snapshot = await drone.snapshot(statuses)
            assert_mission_promises(snapshot, TestbedPlan(mission=PLAN))
        audit = (await drones["alpha"].status(audit=True)).audit
        assert {a.controller_id for a in audit} == {1, 2}
        handovers = (await drones["alpha"].status()).handovers
        assert [(h.old_master, h.new_master) for h in handovers] == [(1, 2)]
        assert handovers[0].trigger == drone_pb2.HANDOVER_TRIGGER_RPC

        # A station that does not answer shows as such in the listing, at once.
        await supervisor.kill("station-3")
        status, out = await fleet_cli(capsys, "missions", "--config", str(network), *registry)
        assert status == 0, out
        assert "2,3?" in out and "3,2?" not in out and "3?,2" in out
        assert "station 3 (" in out and "no answer: UNAVAILABLE" in out
        for channel in [
            *(s.channel for s in stations.values()),
            *(d.channel for d in drones.values()),
        ]:
            await channel.close()
