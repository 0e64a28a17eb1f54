"""The fleet registry: stations and admitted missions in one SQLite file.

The embedded default of issue 34: one file on one node, nothing else to run.
It remembers the stations (name, id, position, radio range) and every mission
admitted (the drone, its route, the ring and the first master the admission
rule chose, its state), across restarts of whatever uses it. Admission runs in
one write transaction (``BEGIN IMMEDIATE``): two submissions for the same
drone at once cannot both be admitted, and a partial unique index on the
missions in flight says so again in the schema.

Nothing in flight needs it: the ring a mission flies with is handed to its
controllers and its drone when it starts, and neither reads the registry.
"""

from __future__ import annotations

import json
import sqlite3
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from baton.drone.policy import Station
from baton.fleet.admission import Admitted, Refused, admit_mission, station_problem
from baton.sdk.types import Position

SCHEMA_VERSION = 2
SCHEMA = """
CREATE TABLE IF NOT EXISTS stations (
    id INTEGER PRIMARY KEY,
    name TEXT NOT NULL UNIQUE,
    latitude_deg REAL NOT NULL,
    longitude_deg REAL NOT NULL,
    range_m REAL NOT NULL,
    drained INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS missions (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    drone TEXT NOT NULL,
    state TEXT NOT NULL CHECK (state IN ('admitted', 'cancelled')),
    route TEXT NOT NULL,
    ring TEXT NOT NULL,
    first_master INTEGER NOT NULL,
    admitted_at REAL NOT NULL,
    drone_address TEXT,
    departed TEXT NOT NULL DEFAULT '[]'
);
CREATE UNIQUE INDEX IF NOT EXISTS one_mission_a_drone ON missions (drone)
    WHERE state = 'admitted';
"""
# Schema 1 to 2: drained stations (``baton fleet drain``), and a mission's drone
# address (``baton fleet start``) and the stations drained out of its ring.
UPGRADE_FROM_1 = """
ALTER TABLE stations ADD COLUMN drained INTEGER NOT NULL DEFAULT 0;
ALTER TABLE missions ADD COLUMN drone_address TEXT;
ALTER TABLE missions ADD COLUMN departed TEXT NOT NULL DEFAULT '[]';
"""
# The states a mission's row can be in: admitted (in flight, as far as the registry
# knows) until cancelled.
IN_FLIGHT = "admitted"


class RegistryError(ValueError):
    """A registry request that cannot be done; the message says why and the fix. The
    subclasses say which kind, for a caller that answers each its own way (the Fleet
    service's status codes); this class itself: a file that is no usable registry."""


class Malformed(RegistryError):
    """A field that can never be taken as given (a station's name, its range)."""


class Taken(RegistryError):
    """A station's name or id that another station holds."""


class Unknown(RegistryError):
    """No station or mission by that name or id."""


class NotInFlight(RegistryError):
    """A mission that is no longer in flight (cancelled) for a request that needs it."""


@dataclass(frozen=True)
class NamedStation:
    """A registered station: its name and what admission needs of it."""

    name: str
    station: Station
    # Drained (baton fleet drain): admitted into no new ring until undrained.
    drained: bool = False


@dataclass(frozen=True)
class MissionRow:
    """An admitted mission as the registry holds it: its ring as admitted, the
    stations drained out of it since (``departed``), and its drone's address once
    ``baton fleet start`` gave it."""

    id: int
    drone: str
    state: str
    route: tuple[Position, ...]
    ring: tuple[int, ...]
    first_master: int
    admitted_at: float
    drone_address: str | None = None
    departed: tuple[int, ...] = ()

    @property
    def live_ring(self) -> tuple[int, ...]:
        """Its ring now: admission's order without the stations drained out of it."""
        return tuple(sid for sid in self.ring if sid not in self.departed)


class Registry:
    """The registry in the SQLite file at ``path`` (made if absent)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self._db = sqlite3.connect(path, isolation_level=None, timeout=10.0)
            version = self._db.execute("PRAGMA user_version").fetchone()[0]
            if version not in (0, 1, SCHEMA_VERSION):
                raise RegistryError(
                    f"{path}: a registry of schema {version}, this baton reads "
                    f"{SCHEMA_VERSION}; use the baton that made it, or another --registry"
                )
            if version == 1:
                self._db.executescript(f"BEGIN; {UPGRADE_FROM_1} COMMIT;")
            self._db.executescript(SCHEMA)
            self._db.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
        except sqlite3.DatabaseError as exc:
            raise RegistryError(
                f"{path}: not a usable registry ({exc}); give another --registry"
            ) from None

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> Registry:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @contextmanager
    def _writing(self) -> Iterator[sqlite3.Connection]:
        """One write transaction, taken before anything is read."""
        self._db.execute("BEGIN IMMEDIATE")
        try:
            yield self._db
        except BaseException:
            self._db.execute("ROLLBACK")
            raise
        self._db.execute("COMMIT")

    def add_station(self, name: str, station: Station) -> None:
        """Registers a station; RegistryError if its name or id is taken or a field is
        malformed."""
        if not name.strip() or name != name.strip():
            raise Malformed(f"name {name!r}: give the station a name, no surrounding blanks")
        problem = station_problem(station)
        if problem is not None:
            raise Malformed(f"{problem[0]}: {problem[1]}")
        location = station.location
        with self._writing() as db:
            for column, value in (("id", station.id), ("name", name)):
                row = db.execute(
                    f"SELECT id, name FROM stations WHERE {column} = ?", (value,)
                ).fetchone()
                if row is not None:
                    raise Taken(
                        f"{column} {value!r} is taken by station {row[1]} (id {row[0]}); "
                        "choose another"
                    )
            db.execute(
                "INSERT INTO stations (id, name, latitude_deg, longitude_deg, range_m) "
                "VALUES (?, ?, ?, ?, ?)",
                (station.id, name, location.latitude_deg, location.longitude_deg, station.range_m),
            )

    def stations(self) -> list[NamedStation]:
        """Every station, by id."""
        return [
            NamedStation(name, Station(sid, Position(lat, lon), range_m), bool(drained))
            for sid, name, lat, lon, range_m, drained in self._db.execute(
                "SELECT id, name, latitude_deg, longitude_deg, range_m, drained FROM stations "
                "ORDER BY id"
            )
        ]

    def station(self, name_or_id: str) -> NamedStation:
        """The station by that name, or else by that id; RegistryError naming the
        stations there are if there is none."""
        stations = self.stations()
        for s in stations:
            if s.name == name_or_id:
                return s
        for s in stations:
            if str(s.station.id) == name_or_id:
                return s
        known = ", ".join(f"{s.name} (id {s.station.id})" for s in stations) or "none"
        raise Unknown(
            f"station {name_or_id!r}: no station by that name or id; the stations: {known}"
        )

    def set_drained(self, name_or_id: str, drained: bool) -> NamedStation:
        """Marks a station drained (admitted into no new ring) or not; RegistryError if
        there is no such station."""
        station = self.station(name_or_id)
        with self._writing() as db:
            db.execute(
                "UPDATE stations SET drained = ? WHERE id = ?", (int(drained), station.station.id)
            )
        return self.station(station.name)

    def set_drone_address(self, mission_id: int, address: str) -> None:
        """Records where the stations reach a mission's drone (``baton fleet start``)."""
        with self._writing() as db:
            db.execute("UPDATE missions SET drone_address = ? WHERE id = ?", (address, mission_id))

    def depart(self, mission_id: int, station_id: int) -> None:
        """Records that a station left a mission's ring (drained out of it)."""
        with self._writing() as db:
            row = db.execute("SELECT departed FROM missions WHERE id = ?", (mission_id,)).fetchone()
            if row is None:
                raise Unknown(f"mission {mission_id}: no such mission")
            departed = sorted({*json.loads(row[0]), station_id})
            db.execute(
                "UPDATE missions SET departed = ? WHERE id = ?", (json.dumps(departed), mission_id)
            )

    def admit(self, drone: str, route: Sequence[Position]) -> tuple[int, Admitted] | Refused:
        """Runs the admission rule over the registered stations and the missions in
        flight, and records the mission if admitted: its id and the admission."""
        with self._writing() as db:
            # A drained station is admitted into no new ring.
            stations = [s.station for s in self.stations() if not s.drained]
            in_flight = {
                d: mid
                for mid, d in db.execute(
                    "SELECT id, drone FROM missions WHERE state = ?", (IN_FLIGHT,)
                )
            }
            decision = admit_mission(drone, route, stations, in_flight)
            if isinstance(decision, Refused):
                return decision
            cursor = db.execute(
                "INSERT INTO missions (drone, state, route, ring, first_master, admitted_at) "
                "VALUES (?, ?, ?, ?, ?, ?)",
                (
                    drone,
                    IN_FLIGHT,
                    json.dumps([[p.latitude_deg, p.longitude_deg] for p in route]),
                    json.dumps(list(decision.ring)),
                    decision.first_master,
                    time.time(),
                ),
            )
            assert cursor.lastrowid is not None
            return cursor.lastrowid, decision

    def withdraw(self, mission_id: int) -> None:
        """Forgets a mission admitted a moment ago whose sessions did not start (admit
        with start): it was never in flight. Its id is not given again (AUTOINCREMENT),
        so a station folder named after it can only be its own."""
        with self._writing() as db:
            db.execute("DELETE FROM missions WHERE id = ? AND state = ?", (mission_id, IN_FLIGHT))

    def missions(self) -> list[MissionRow]:
        """Every mission ever admitted, by id."""
        return [
            MissionRow(
                mid,
                drone,
                state,
                tuple(Position(lat, lon) for lat, lon in json.loads(route)),
                tuple(json.loads(ring)),
                first_master,
                admitted_at,
                drone_address,
                tuple(json.loads(departed)),
            )
            for (
                mid,
                drone,
                state,
                route,
                ring,
                first_master,
                admitted_at,
                drone_address,
                departed,
            ) in self._db.execute(
                "SELECT id, drone, state, route, ring, first_master, admitted_at, drone_address, "
                "departed FROM missions ORDER BY id"
            )
        ]

    def mission(self, mission_id: int) -> MissionRow:
        """The mission with that id; RegistryError if there is none."""
        for mission in self.missions():
            if mission.id == mission_id:
                return mission
        raise Unknown(f"mission {mission_id}: no such mission; baton fleet missions lists them")

    def cancel(self, mission_id: int) -> MissionRow:
        """Cancels a mission in flight; RegistryError if there is none by that id."""
        with self._writing() as db:
            row = db.execute("SELECT state FROM missions WHERE id = ?", (mission_id,)).fetchone()
            if row is None:
                raise Unknown(
                    f"mission {mission_id}: no such mission; baton fleet missions lists them"
                )
            if row[0] != IN_FLIGHT:
                raise NotInFlight(f"mission {mission_id}: already {row[0]}")
            db.execute("UPDATE missions SET state = 'cancelled' WHERE id = ?", (mission_id,))
        return next(m for m in self.missions() if m.id == mission_id)
