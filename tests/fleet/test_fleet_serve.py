"""``baton fleet serve`` across real processes: the Fleet service over a registry and
two real ``baton station`` processes, called with grpc and grpcurl as the operator
(and refused to any other certificate); ``baton fleet admit --start`` beside it on
the same registry."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable
from pathlib import Path

import grpc
import pytest
from helpers.drone_calls import refused_details
from helpers.missions import SMALL_GRID
from helpers.stations import fleet_cli, hosted, network_file, start_fleet_service

from baton.certs.make import init
from baton.config import BatonConfig
from baton.rpc.channels import aio_channel
from baton.rpc.tls import DRONE, OPERATOR, Identity, Tls
from baton.testbed.fleet import start_stations
from baton.testbed.supervisor import Supervisor
from baton.v1 import fleet_pb2, fleet_pb2_grpc, station_pb2

PLACES = {1: (47.398191, 8.545594), 2: (47.398191, 8.552229)}
TAKE_OFF = (47.397742, 8.545594)
EAST = (47.397742, 8.550)
# 3.3 km east: beyond station 2's range from about 1 km on.
FAR = (47.397742, 8.59)
HOSTING = station_pb2.SESSION_STATE_HOSTING


def place(at: tuple[float, float]) -> fleet_pb2.Place:
    return fleet_pb2.Place(latitude_deg=at[0], longitude_deg=at[1])


async def test_the_fleet_service_admits_starts_refuses_lists_and_cancels(
    tmp_path: Path, grpcurl: Callable[..., str], capsys: pytest.CaptureFixture[str]
) -> None:
    certs = tmp_path / "certs"
    init(certs, [Identity.controller(1), Identity.controller(2), DRONE, OPERATOR])
    registry = tmp_path / "fleet.sqlite"
    program, args = str(SMALL_GRID.file), SMALL_GRID.args()
    async with Supervisor(tmp_path / "parts") as supervisor:
        # No drone: the sessions wait for it.
        stations = await start_stations(supervisor, (1, 2), certs)
        network = network_file(tmp_path / "network.yaml", stations, PLACES, 500, certs)
        address = await start_fleet_service(supervisor, registry, network, certs)

        async def curl(*args: str) -> str:
            """grpcurl as docs/operating.md shows it: the operator, -servername operator.baton."""
            return await asyncio.to_thread(grpcurl, *args, certs=certs, peer=OPERATOR.dns_name)

        async with aio_channel(address, Tls.load(certs, OPERATOR), OPERATOR) as channel:
            fleet: fleet_pb2_grpc.FleetAsyncStub = fleet_pb2_grpc.FleetStub(channel)  # type: ignore[no-untyped-call]
            assert "baton.v1.Fleet" in (await curl(address, "list")).split()
            for sid, at in PLACES.items():
                await fleet.AddStation(
                    fleet_pb2.AddStationRequest(
                        name=f"s{sid}", id=sid, location=place(at), range_m=500
                    )
                )
            listed = json.loads(await curl(address, "baton.v1.Fleet/ListStations"))
            assert [(s["name"], s.get("id", 0)) for s in listed["stations"]] == [
                ("s1", 1),
                ("s2", 2),
            ]

            # A stretch no station covers: refused, the stretch named, nothing admitted.
            details = await refused_details(
                fleet.Admit(
                    fleet_pb2.AdmitRequest(drone="d1", route=[place(TAKE_OFF), place(FAR)])
                ),
                grpc.StatusCode.FAILED_PRECONDITION,
            )
            assert "refused: route: a stretch no station covers: from (47.397742, 8.5" in details
            assert "to (47.397742, 8.590000) at 3346 m" in details

            # A start that fails on station 2 is undone on station 1, and the mission is
            # not admitted: the drone is free again.
            await supervisor.kill("station-2")
            route = [place(TAKE_OFF), place(EAST)]
            details = await refused_details(
                fleet.Admit(
                    fleet_pb2.AdmitRequest(
                        drone="d1", route=route, start=True, program=program, args=args
                    )
                ),
                grpc.StatusCode.UNAVAILABLE,
            )
            assert details.startswith("not admitted: not started: station 2"), details
            assert "stopped on 1" in details
            assert await hosted(stations[1]) == {}
            missions = await fleet.ListMissions(fleet_pb2.ListMissionsRequest())
            assert list(missions.missions) == []
            await supervisor.restart("station-2")

            # Admitted and started, over grpcurl: the reply names the ring and carries
            # the configuration the drone takes its ring from.
            submission = {
                "drone": "d1",
                "route": [{"latitude_deg": a, "longitude_deg": b} for a, b in (TAKE_OFF, EAST)],
                "start": True,
                "program": program,
                "args": args,
            }
            reply = json.loads(
                await curl("-d", json.dumps(submission), address, "baton.v1.Fleet/Admit")
            )
            # The withdrawn admission's id is not given again.
            assert reply.get("mission_id") == "2" and reply.get("started") is True, reply
            assert [s["id"] for s in reply["ring"]] == [1, 2] and reply["first_master"] == 1
            config = BatonConfig.model_validate_json(reply["mission_config"])
            assert config.ring_order == [1, 2] and config.master_id == 1
            assert all(c.location is not None and c.range_m == 500 for c in config.controllers)
            for station in stations.values():
                assert await hosted(station) == {"2": HOSTING}

            details = await refused_details(
                fleet.Admit(fleet_pb2.AdmitRequest(drone="d1", route=route)),
                grpc.StatusCode.ALREADY_EXISTS,
            )
            assert "refused: drone: 'd1' already flies mission 2" in details

            missions = await fleet.ListMissions(fleet_pb2.ListMissionsRequest())
            (flying,) = missions.missions
            assert (flying.id, flying.drone, flying.state, list(flying.ring)) == (
                2,
                "d1",
                "admitted",
                [1, 2],
            )
            assert flying.asked and list(flying.silent) == []
            status = await fleet.GetMission(fleet_pb2.GetMissionRequest(mission_id=2))
            assert sorted(status.sessions) == [1, 2]
            for sid, session in status.sessions.items():
                assert session.WhichOneof("answer") == "status", session
                assert (session.status.id, session.status.mission_id) == (sid, "2")
            assert status.WhichOneof("drone") == "drone_error"  # no drone at its address
            details = await refused_details(
                fleet.GetMission(fleet_pb2.GetMissionRequest(mission_id=7)),
                grpc.StatusCode.NOT_FOUND,
            )
            assert "mission 7: no such mission" in details

            cancelled = json.loads(
                await curl("-d", '{"mission_id": 2}', address, "baton.v1.Fleet/CancelMission")
            )
            assert cancelled["mission"]["state"] == "cancelled"
            assert cancelled["stopped_on"] == [1, 2]
            for station in stations.values():
                assert await hosted(station) == {}
                assert not (station.state_dir / "missions" / "2").exists()

        # Only the operator: a station's certificate is refused before its request is read.
        controller = Tls.load(certs, Identity.controller(1))
        async with aio_channel(address, controller, OPERATOR) as channel:
            stub: fleet_pb2_grpc.FleetAsyncStub = fleet_pb2_grpc.FleetStub(channel)  # type: ignore[no-untyped-call]
            details = await refused_details(
                stub.ListStations(fleet_pb2.ListStationsRequest()),
                grpc.StatusCode.PERMISSION_DENIED,
            )
            assert "only an operator (spiffe://baton/operator) may" in details

        # The command admits and starts over the same registry the service serves, and
        # writes the drone's configuration.
        drone_config = tmp_path / "d3.json"
        status_code, out = await fleet_cli(
            capsys,
            "admit",
            "--drone=d3",
            "--route",
            ",".join(map(str, TAKE_OFF)),
            ",".join(map(str, EAST)),
            "--start",
            f"--config={network}",
            f"--mission={SMALL_GRID.file}",
            *(f"--mission-arg={arg}" for arg in SMALL_GRID.args()),
            f"--drone-config={drone_config}",
            f"--registry={registry}",
        )
        assert status_code == 0, out
        assert "mission 3 admitted for drone d3" in out
        assert "mission 3 of drone d3 started on stations 1 (first master), 2" in out
        assert BatonConfig.model_validate_json(drone_config.read_text()).ring_order == [1, 2]
        assert await hosted(stations[1]) == {"3": HOSTING}
        status_code, out = await fleet_cli(
            capsys, "cancel", "3", f"--config={network}", f"--registry={registry}"
        )
        assert status_code == 0, out
        for station in stations.values():
            await station.channel.close()
