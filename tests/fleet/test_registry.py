"""The fleet registry: stations and admitted missions in one SQLite file, kept across
restarts, one mission in flight a drone."""

from __future__ import annotations

import sqlite3
import threading
from pathlib import Path

import pytest

from baton.drone.policy import Station
from baton.fleet.admission import Admitted, Refused
from baton.fleet.registry import Registry, RegistryError
from baton.sdk import Position, offset

HOME = Position(47.397742, 8.545594)
ROUTE = [HOME, offset(HOME, 0, 600)]


def two_stations(path: Path) -> Registry:
    registry = Registry(path)
    registry.add_station("west", Station(0, HOME, 400))
    registry.add_station("east", Station(1, offset(HOME, 0, 600), 400))
    return registry


def test_stations_and_missions_survive_a_restart(tmp_path: Path) -> None:
    path = tmp_path / "fleet.sqlite"
    registry = two_stations(path)
    admitted = registry.admit("d1", ROUTE)
    assert not isinstance(admitted, Refused)
    registry.close()

    again = Registry(path)
    assert [(s.name, s.station.id) for s in again.stations()] == [("west", 0), ("east", 1)]
    [mission] = again.missions()
    assert (mission.id, mission.drone, mission.state) == (admitted[0], "d1", "admitted")
    assert mission.ring == (0, 1) and mission.first_master == 0
    assert mission.route[-1].longitude_deg == pytest.approx(ROUTE[-1].longitude_deg)
    # The drone is still busy after the restart, and free once its mission is cancelled.
    busy = again.admit("d1", ROUTE)
    assert isinstance(busy, Refused) and busy.field == "drone"
    again.cancel(mission.id)
    assert isinstance(again.admit("d1", ROUTE), tuple)


def test_a_refused_mission_leaves_nothing(tmp_path: Path) -> None:
    registry = two_stations(tmp_path / "fleet.sqlite")
    refused = registry.admit("d1", [HOME, offset(HOME, 0, 2000)])
    assert isinstance(refused, Refused) and refused.uncovered
    assert registry.missions() == []


def test_a_station_name_or_id_taken_is_refused(tmp_path: Path) -> None:
    registry = two_stations(tmp_path / "fleet.sqlite")
    with pytest.raises(RegistryError, match="name 'west' is taken by station west"):
        registry.add_station("west", Station(5, HOME, 10))
    with pytest.raises(RegistryError, match="id 1 is taken by station east"):
        registry.add_station("north", Station(1, HOME, 10))
    with pytest.raises(RegistryError, match="range_m: 0: must be > 0"):
        registry.add_station("north", Station(2, HOME, 0))
    assert len(registry.stations()) == 2


def test_two_submissions_for_one_drone_at_once_admit_one(tmp_path: Path) -> None:
    # Each from its own connection, as two operators' commands would be: the write
    # transaction taken before reading the missions in flight lets one through.
    path = tmp_path / "fleet.sqlite"
    two_stations(path).close()
    start = threading.Barrier(4)
    results: list[tuple[int, Admitted] | Refused] = []

    def submit() -> None:
        registry = Registry(path)
        start.wait()
        results.append(registry.admit("d1", ROUTE))
        registry.close()

    threads = [threading.Thread(target=submit) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    admitted = [r for r in results if isinstance(r, tuple)]
    assert len(admitted) == 1 and len(results) == 4
    assert all(r.field == "drone" for r in results if isinstance(r, Refused))
    assert len(Registry(path).missions()) == 1


def test_the_schema_itself_allows_one_mission_in_flight_a_drone(tmp_path: Path) -> None:
    path = tmp_path / "fleet.sqlite"
    two_stations(path).admit("d1", ROUTE)
    db = sqlite3.connect(path)
    with pytest.raises(sqlite3.IntegrityError):
        db.execute(
            "INSERT INTO missions (drone, state, route, ring, first_master, admitted_at) "
            "VALUES ('d1', 'admitted', '[]', '[]', 0, 0)"
        )


def test_a_file_that_is_not_a_registry_is_named(tmp_path: Path) -> None:
    path = tmp_path / "notes.txt"
    path.write_text("not a database, only words in a file " * 10)
    with pytest.raises(RegistryError, match=f"{path}: not a usable registry"):
        Registry(path)
