"""What the live fleet view shows, decided from what the network reports: pure.

``fleet_view`` takes the registry's stations and missions, each station's
``GetStation`` reply and each mission's drone's ``GetStatus`` reply (or, for
a part that did not answer, the line saying why) and returns the one
document the page draws, as JSON-ready data. The page keeps no state of its
own but a drone's trail, so what it shows is this function of the reports.

Places are metres east and north of the lowest-numbered station (no map
tiles: the page draws stations, ranges and drones on its own grid). A
drone's master is its own word when it answers (it is the one that switches),
else the sessions' (``operations.overview``: the newest epoch that says so);
its mission's state and progress are the sessions' (``overview``). A part
that did not answer is listed under ``problems`` and drawn as silent, never
left out: an operator sees a station go quiet.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from baton.fleet.operations import overview, session_statuses
from baton.fleet.registry import IN_FLIGHT, MissionRow, NamedStation
from baton.sdk.geo import north_east_m
from baton.sdk.types import Position
from baton.testbed.flight_map import colour
from baton.v1 import drone_pb2, station_pb2

# The document's format; the page refuses another.
VIEW_FORMAT = "baton.fleet.view/1"
# Room around what is drawn, metres.
MARGIN_M = 50.0


def _metres(origin: Position, latitude_deg: float, longitude_deg: float) -> dict[str, float]:
    north, east = north_east_m(origin, Position(latitude_deg, longitude_deg))
    return {"east_m": round(east, 2), "north_m": round(north, 2)}


def _station(
    origin: Position, named: NamedStation, reply: station_pb2.StationStatus | str | None
) -> dict[str, Any]:
    s = named.station
    answering = isinstance(reply, station_pb2.StationStatus)
    hosted = sorted(m.mission_id for m in reply.missions) if answering else []  # type: ignore[union-attr]
    return {
        "id": s.id,
        "name": named.name,
        **_metres(origin, s.location.latitude_deg, s.location.longitude_deg),
        "range_m": s.range_m,
        "drained": named.drained,
        "answering": answering,
        "missions": hosted,
        "colour": colour(s.id),
    }


def _drone(
    origin: Position,
    mission: MissionRow,
    replies: Mapping[int, station_pb2.StationStatus | str],
    drone: drone_pb2.DroneStatus | str,
) -> tuple[dict[str, Any], list[str]]:
    sessions = session_statuses(mission, dict(replies))
    seen = overview(sessions)
    problems = list(seen.silent)
    place: dict[str, float] | None = None
    master = seen.master
    epoch = None
    if isinstance(drone, str):
        problems.append(f"mission {mission.id} ({mission.drone}): {drone}")
    else:
        p = drone.position
        if p.latitude_deg != 0 or p.longitude_deg != 0:  # all zero: not known yet
            place = _metres(origin, p.latitude_deg, p.longitude_deg)
        master, epoch = drone.master, drone.epoch
    return (
        {
            "drone": mission.drone,
            "mission": mission.id,
            "ring": list(mission.live_ring),
            "place": place,
            "master": master,
            "epoch": epoch,
            "state": seen.state,
            "reqnr": seen.reqnr,
            "answering": not isinstance(drone, str),
            "colour": colour(master) if master is not None else "#7f7f7f",
        },
        problems,
    )


def _bounds(stations: Sequence[dict[str, Any]], drones: Sequence[dict[str, Any]]) -> list[float]:
    """[west, south, east, north] metres: every range and every drone, with a margin."""
    xs: list[float] = []
    ys: list[float] = []
    for s in stations:
        xs += [s["east_m"] - s["range_m"], s["east_m"] + s["range_m"]]
        ys += [s["north_m"] - s["range_m"], s["north_m"] + s["range_m"]]
    for d in drones:
        if d["place"] is not None:
            xs.append(d["place"]["east_m"])
            ys.append(d["place"]["north_m"])
    if not xs:
        return [-MARGIN_M, -MARGIN_M, MARGIN_M, MARGIN_M]
    return [
        round(min(xs) - MARGIN_M, 2),
        round(min(ys) - MARGIN_M, 2),
        round(max(xs) + MARGIN_M, 2),
        round(max(ys) + MARGIN_M, 2),
    ]


def fleet_view(
    stations: Sequence[NamedStation],
    missions: Sequence[MissionRow],
    station_replies: Mapping[int, station_pb2.StationStatus | str],
    drone_replies: Mapping[int, drone_pb2.DroneStatus | str],
    at: float,
) -> dict[str, Any]:
    """The page's document at time ``at`` (Unix seconds): the stations with their ranges
    and whether they answer, each mission in flight's drone with its place, master,
    state and progress, the bounds to draw, and what did not answer.
    ``drone_replies`` is by mission id; a mission without one counts as silent."""
    ordered = sorted(stations, key=lambda n: n.station.id)
    origin = ordered[0].station.location if ordered else Position(0.0, 0.0)
    problems: list[str] = []
    drawn_stations = []
    for named in ordered:
        reply = station_replies.get(named.station.id)
        if isinstance(reply, str):
            problems.append(reply)
        drawn_stations.append(_station(origin, named, reply))
    drones = []
    for mission in sorted(missions, key=lambda m: m.id):
        if mission.state != IN_FLIGHT:
            continue
        drone = drone_replies.get(mission.id, f"drone of mission {mission.id}: not asked")
        drawn, said = _drone(origin, mission, station_replies, drone)
        drones.append(drawn)
        problems += [p for p in said if p not in problems]
    return {
        "format": VIEW_FORMAT,
        "at": round(at, 3),
        "origin": [origin.latitude_deg, origin.longitude_deg],
        "bounds": _bounds(drawn_stations, drones),
        "stations": drawn_stations,
        "drones": drones,
        "problems": problems,
    }


def changed(before: Mapping[str, Any] | None, after: Mapping[str, Any]) -> bool:
    """Whether ``after`` shows anything ``before`` did not (its time aside): the page is
    sent a document only then."""
    if before is None:
        return True
    return {k: v for k, v in before.items() if k != "at"} != {
        k: v for k, v in after.items() if k != "at"
    }
