"""Draining a station: which rings can do without it, and where each master it holds
goes. Pure: the operations (``operations.py``, ``baton fleet drain``) ask the
stations and the drones, feed their word here, and carry the answer out.

A ring can do without station S when, S left out:

- at least ``MIN_RING`` stations remain: a ring of one has no replica to take
  over from its master, which is the whole point of the ring;
- the stations that remain cover the *remaining* route (admission's exact
  coverage, ``admission.covered_intervals``), and the drone where it is now:
  a stretch only S covers is a stretch where the drone would have no master
  it can reach. The remaining route starts where the drone is along its route
  (the nearest point of the route to its position, the earliest leg when two
  are as near, so that a crossing route is never cut short); when the drone's
  position is unknown, or it is farther than ``OFF_ROUTE_M`` from its route
  (returning home, blown off), the whole route remains.

A ring that cannot do without S keeps it: its session stays, its master does
not move, and the drain says why. A ring that can loses S: if S is its master,
the master is handed over first (``handover_target``), then S's session is
stopped and the other stations route around it as around a dead controller.
The drone never makes S master again: its policy chooses only stations whose
link is up, and a stopped session holds no link.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from baton.drone.policy import Station
from baton.fleet.admission import TOUCHING_M, FlatRoute, covered_intervals, gaps
from baton.sdk.geo import north_east_m
from baton.sdk.types import Position

# The fewest stations a ring keeps: a master and one replica.
MIN_RING = 2
# Farther than this from every leg of its route, a drone's place along it is unknown.
OFF_ROUTE_M = 50.0


@dataclass(frozen=True)
class MissionView:
    """What the drain knows of one mission: its ring now (admission's order, the
    stations that left it already gone), its route, where its stations are, its
    master (None: no one said) and its drone's position (None: unknown)."""

    mission_id: int
    ring: tuple[int, ...]
    route: tuple[Position, ...]
    stations: Mapping[int, Station]
    master: int | None
    drone_at: Position | None
    # Stations drained already that stay in this ring (it could not do without them).
    drained: frozenset[int] = frozenset()


@dataclass(frozen=True)
class Leave:
    """The station leaves the mission's ring; ``hand_over_to`` first if it is its master."""

    mission_id: int
    hand_over_to: int | None


@dataclass(frozen=True)
class Stay:
    """The station stays in the mission's ring: the reason, for a person."""

    mission_id: int
    reason: str


def drain_mission(station: int, mission: MissionView) -> Leave | Stay:
    """Whether ``station`` may leave ``mission``'s ring, and where its master goes."""
    if station not in mission.ring:
        raise ValueError(f"station {station} is not in mission {mission.mission_id}'s ring")
    rest = tuple(sid for sid in mission.ring if sid != station)
    if len(rest) < MIN_RING:
        return Stay(
            mission.mission_id,
            f"its ring {list(mission.ring)} would keep {len(rest)} station, fewer than "
            f"{MIN_RING} (a master and a replica); cancel the mission or let it end",
        )
    others = [mission.stations[sid] for sid in rest]
    if mission.drone_at is not None and not any(_holds(s, mission.drone_at) for s in others):
        where = mission.drone_at
        return Stay(
            mission.mission_id,
            f"its drone is at ({where.latitude_deg:.6f}, {where.longitude_deg:.6f}), in "
            f"no other station's range of its ring {list(mission.ring)}; drain again once "
            "it has flown on",
        )
    remaining, from_m = remaining_route(mission.route, mission.drone_at)
    spans = covered_intervals(remaining, others)
    flat = FlatRoute.of(remaining)
    uncovered = gaps(sorted(span for s in spans.values() for span in s), flat.length_m)
    if uncovered:
        start, end = uncovered[0]
        a, b = flat.at(start), flat.at(end)
        return Stay(
            mission.mission_id,
            f"only station {station} of its ring covers the route from "
            f"({a.latitude_deg:.6f}, {a.longitude_deg:.6f}) at {from_m + start:.0f} m "
            f"to ({b.latitude_deg:.6f}, {b.longitude_deg:.6f}) at {from_m + end:.0f} m "
            "along it, still to fly; drain again once the drone is past it",
        )
    target = None
    if mission.master == station:
        target = handover_target(
            station, mission.ring, mission.stations, mission.drone_at, mission.drained
        )
    return Leave(mission.mission_id, target)


def handover_target(
    station: int,
    ring: Sequence[int],
    stations: Mapping[int, Station],
    drone_at: Position | None,
    drained: frozenset[int] = frozenset(),
) -> int:
    """Where a master on ``station`` goes: the next station after it in ring order
    whose range holds the drone now, or, with none (or the drone's position
    unknown), the ring's next after it. Among those, stations drained already
    come after the others (a master moved onto one would move again when it is
    drained out), but before none that holds the drone."""
    k = ring.index(station)
    after = [ring[(k + step) % len(ring)] for step in range(1, len(ring))]
    after.sort(key=lambda sid: sid in drained)  # stable: ring order otherwise
    if drone_at is not None:
        for sid in after:
            if _holds(stations[sid], drone_at):
                return sid
    return after[0]


def remaining_route(
    route: Sequence[Position], drone_at: Position | None
) -> tuple[tuple[Position, ...], float]:
    """The route still to fly from ``drone_at``, and how far along the route it starts
    (metres): from the nearest point of the route on (the earliest leg of those as
    near); the whole route when the position is unknown or off the route."""
    if drone_at is None or len(route) < 2:
        return tuple(route), 0.0
    flat = FlatRoute.of(route)
    here = north_east_m(flat.origin, drone_at)
    best: tuple[float, int, float] | None = None  # distance, leg, metres along it
    for k, (along, start, end) in enumerate(flat.legs()):
        t, distance = _nearest_on_leg(start, end, here)
        if best is None or distance < best[0] - TOUCHING_M:
            best = (distance, k, along + t)
    assert best is not None
    distance, leg, at_m = best
    if distance > OFF_ROUTE_M:
        return tuple(route), 0.0
    return (flat.at(at_m), *route[leg + 1 :]), at_m


def _nearest_on_leg(
    start: tuple[float, float], end: tuple[float, float], point: tuple[float, float]
) -> tuple[float, float]:
    """The metres from ``start`` of the leg's point nearest ``point``, and its distance."""
    dn, de = end[0] - start[0], end[1] - start[1]
    length = math.hypot(dn, de)
    pn, pe = point[0] - start[0], point[1] - start[1]
    t = 0.0 if length <= 0 else min(max((pn * dn + pe * de) / length, 0.0), length)
    if length > 0:
        nn, ne = start[0] + dn * t / length, start[1] + de * t / length
    else:
        nn, ne = start
    return t, math.hypot(point[0] - nn, point[1] - ne)


def _holds(station: Station, where: Position) -> bool:
    north, east = north_east_m(station.location, where)
    return math.hypot(north, east) <= station.range_m
