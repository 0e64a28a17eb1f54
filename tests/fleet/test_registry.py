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


def test_a_drained_station_is_in_no_new_ring_until_undrained(tmp_path: Path) -> None:
    with two_stations(tmp_path / "fleet.sqlite") as registry:
        assert registry.set_drained("east", True).drained
        refused = registry.admit("d1", ROUTE)
        assert isinstance(refused, Refused) and refused.field == "route"
        assert registry.set_drained("1", False) == registry.station("east")
        admitted = registry.admit("d1", ROUTE)
        assert not isinstance(admitted, Refused) and admitted[1].ring == (0, 1)
        with pytest.raises(RegistryError, match=r"'north': no station by that name or id; "):
            registry.set_drained("north", True)

        # A station drained out of a ring leaves it; the admitted ring is kept.
        registry.set_drone_address(admitted[0], "127.0.0.1:5")
        registry.depart(admitted[0], 0)
        [mission] = registry.missions()
        assert (mission.ring, mission.live_ring, mission.departed) == ((0, 1), (1,), (0,))
        assert mission.drone_address == "127.0.0.1:5"


def test_a_schema_1_registry_is_upgraded_in_place(tmp_path: Path) -> None:
    path = tmp_path / "fleet.sqlite"
    db = sqlite3.connect(path)
    db.executescript(
        """
        CREATE TABLE stations (id INTEGER PRIMARY KEY, name TEXT NOT NULL UNIQUE,
            latitude_deg REAL NOT NULL, longitude_deg REAL NOT NULL, range_m REAL NOT NULL);
        CREATE TABLE missions (id INTEGER PRIMARY KEY AUTOINCREMENT, drone TEXT NOT NULL,
            state TEXT NOT NULL, route TEXT NOT NULL, ring TEXT NOT NULL,
            first_master INTEGER NOT NULL, admitted_at REAL NOT NULL);
        INSERT INTO stations VALUES (0, 'west', 47.397742, 8.545594, 400);
        INSERT INTO missions VALUES (1, 'd1', 'admitted', '[[47.397742, 8.545594]]', '[0]', 0, 0);
        PRAGMA user_version = 1;
        """
    )
    db.close()
    with Registry(path) as registry:
        [station] = registry.stations()
        assert (station.name, station.drained) == ("west", False)
        [mission] = registry.missions()
        assert (mission.live_ring, mission.drone_address) == ((0,), None)
