"""``baton fleet start`` and ``cancel`` against real station processes: an admitted
mission's sessions start on its whole ring or on none, a restarted station takes its
session back from its history file, and a cancel leaves nothing."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.missions import SMALL_GRID
from helpers.stations import fleet_cli, hosted, network_file

from baton.certs.make import init
from baton.rpc.tls import DRONE, OPERATOR, Identity
from baton.testbed.fleet import start_stations
from baton.testbed.supervisor import Supervisor
from baton.v1 import station_pb2

TAKE_OFF, EAST = "47.397742,8.545594", "47.397742,8.550"
PLACES = {1: (47.398191, 8.545594), 2: (47.398191, 8.552229)}


async def test_a_ring_starts_whole_or_not_at_all_again_after_a_restart_and_cancels_to_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    certs = tmp_path / "certs"
    init(certs, [Identity.controller(1), Identity.controller(2), DRONE, OPERATOR])
    registry = ["--registry", str(tmp_path / "fleet.sqlite")]
    async with Supervisor(tmp_path / "parts") as supervisor:
        stations = await start_stations(supervisor, (1, 2), certs)
        # No drone: the sessions wait for it.
        network = network_file(tmp_path / "network.yaml", stations, PLACES, 500, certs)
        status, out = await fleet_cli(
            capsys, "stations", "add", "--from-config", str(network), *registry
        )
        assert status == 0, out
        status, out = await fleet_cli(
            capsys, "admit", "--drone", "d1", "--route", TAKE_OFF, EAST, *registry
        )
        assert status == 0 and "mission 1 admitted" in out, out
        start = ["start", "1", "--config", str(network), "--mission", str(SMALL_GRID.file)]
        start += [f"--mission-arg={arg}" for arg in SMALL_GRID.args()] + registry

        # Station 2 is down: the start fails there and is undone on station 1, which
        # keeps nothing of it.
        await supervisor.kill("station-2")
        status, out = await fleet_cli(capsys, *start)
        assert status == 1, out
        assert "station 2" in out and "UNAVAILABLE" in out and "stopped on 1" in out
        assert await hosted(stations[1]) == {}
        assert not (stations[1].state_dir / "missions" / "1").exists()
        await supervisor.restart("station-2")

        status, out = await fleet_cli(capsys, *start)
        assert status == 0, out
        assert "started on stations 1 (first master), 2" in out
        for station in stations.values():
            assert await hosted(station) == {"1": station_pb2.SESSION_STATE_HOSTING}
            session = await station.status("1")
            assert (session.id, session.mission_id) == (station.id, "1")

        # Station 2 restarted has no session but its history file: starting the mission
        # again takes the session back there from it, and leaves station 1's running.
        history = stations[2].state_dir / "missions" / "1" / "history.sqlite"
        await supervisor.kill("station-2")
        await supervisor.restart("station-2")
        assert await hosted(stations[2]) == {} and history.exists()
        before = (await stations[1].status("1")).log_file
        status, out = await fleet_cli(capsys, *start)
        assert status == 0, out
        assert (await stations[2].status("1")).log_file.path == str(history)
        assert await hosted(stations[1]) == {"1": station_pb2.SESSION_STATE_HOSTING}
        assert (await stations[1].status("1")).log_file == before

        status, out = await fleet_cli(capsys, "cancel", "1", "--config", str(network), *registry)
        assert status == 0 and "cancelled" in out, out
        for station in stations.values():
            assert await hosted(station) == {}
            assert not (station.state_dir / "missions" / "1").exists()
        status, out = await fleet_cli(capsys, "missions", *registry)
        assert "cancelled" in out
        for station in stations.values():
            await station.channel.close()
