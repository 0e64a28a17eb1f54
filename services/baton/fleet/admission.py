"""Mission admission: which stations cover a route, the ring, and the first master.

The paper's deployment: "N edge nodes selected to host the instances of the
mission controller so as to cover the entire path of the drone". This module
is that choice, as a pure function (``admit_mission``): it takes the stations (id,
position, radio range, the handover policy's ``Station``), the drone and its
route (take-off first, then the positions flown to in order), and the
missions in flight by drone, and returns an ``Admitted`` (the ring and the
first master) or a ``Refused`` naming the field and what is wrong. No
database, no sockets, no clock: the registry (``registry.py``) and the
testbed feed it and carry out its answer.

The rules:

- Every point of the route must be in some station's range (on the circle
  counts, as for the handover policy); a stretch that none covers refuses the
  mission, each such stretch named from where to where (lat/lon) and at which
  metres along the route.
- The ring is the stations whose range the route enters, in the order it
  first enters them; stations it enters at the same point are ordered by
  their distance to that point, then by id. Stations the route never enters
  are not in the ring.
- The first master is the station nearest take-off among those whose range
  holds it (ties: the lower id): the first of the ring, by the rule above.
- A drone with a mission in flight is refused (field ``drone``); a malformed
  submission is refused naming the field (``route[3].latitude_deg``,
  ``stations[1].range_m``).

Coverage is computed exactly, not by sampling: the vehicle flies each leg as a
straight line (the drone API's Goto) and a range is a disc, which is convex,
so a leg meets a range in one interval whose ends are the roots of a
quadratic. A sampled leg could step over a gap narrower than its step; the
intervals cannot. Distances are horizontal, on one flat Earth around take-off
(``baton.sdk.geo``, good to centimetres over a few kilometres); a route
reaching farther than ``MAX_REACH_M`` from take-off is refused, since the
flat Earth no longer holds there.
"""

from __future__ import annotations

import bisect
import enum
import itertools
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass

from baton.drone.policy import Station
from baton.sdk.geo import north_east_m, offset
from baton.sdk.types import Position

# Farthest a route point may be from take-off, metres: the flat Earth's error grows
# with the square of the distance (about 1 m at 50 km at mid latitudes).
MAX_REACH_M = 50_000.0
# Two covered intervals closer than this (metres along the route) are one: the ends
# of two ranges that touch, computed on two circles, differ by rounding only.
TOUCHING_M = 1e-6
# A station's id is the controller id of its ring (config.ControllerConfig.id).
MAX_STATION_ID = 2**31 - 1


@dataclass(frozen=True)
class Stretch:
    """A part of the route: from ``from_m`` to ``to_m`` metres along it, between the
    positions ``start`` and ``end``."""

    from_m: float
    to_m: float
    start: Position
    end: Position

    def describe(self) -> str:
        """For a person: where it starts and ends, and how long it is."""
        return (
            f"from ({self.start.latitude_deg:.6f}, {self.start.longitude_deg:.6f}) at "
            f"{self.from_m:.0f} m along the route to ({self.end.latitude_deg:.6f}, "
            f"{self.end.longitude_deg:.6f}) at {self.to_m:.0f} m "
            f"({self.to_m - self.from_m:.0f} m)"
        )


@dataclass(frozen=True)
class Admitted:
    """The mission's ring (station ids in route order), its first master, and where
    along the route (metres) each station's range is first entered."""

    ring: tuple[int, ...]
    first_master: int
    enters_at_m: Mapping[int, float]
    length_m: float


class Refusal(enum.Enum):
    """What kind of refusal: a submission that can never be admitted as sent
    (``MALFORMED``), a drone that flies a mission already (``BUSY``), a route the
    stations do not cover (``UNCOVERED``), or no station to cover anything
    (``NO_STATIONS``); the last two could be admitted once stations are added."""

    MALFORMED = "malformed"
    BUSY = "busy"
    UNCOVERED = "uncovered"
    NO_STATIONS = "no stations"


@dataclass(frozen=True)
class Refused:
    """Why a submission is refused: the field at fault and what is wrong with it;
    the uncovered stretches when the route has any."""

    field: str
    reason: str
    uncovered: tuple[Stretch, ...] = ()
    kind: Refusal = Refusal.MALFORMED

    def message(self) -> str:
        """One line for a person: ``FIELD: what is wrong``."""
        return f"{self.field}: {self.reason}"


def admit_mission(
    drone: str,
    route: Sequence[Position],
    stations: Sequence[Station],
    in_flight: Mapping[str, int],
) -> Admitted | Refused:
    """Admits ``drone``'s ``route`` over ``stations``, or says why not.

    ``in_flight``: the missions in flight by drone (drone -> mission id): a drone in
    it is refused. Checks in order: the submission's fields, the drone, coverage.
    """
    malformed = check_submission(drone, route, stations)
    if malformed is not None:
        return malformed
    if drone in in_flight:
        return Refused(
            "drone",
            f"{drone!r} already flies mission {in_flight[drone]}; cancel it first "
            "(baton fleet cancel), or submit for another drone",
            kind=Refusal.BUSY,
        )
    flat = FlatRoute.of(route)
    intervals = _covered(flat, stations)
    missing = gaps(sorted(span for spans in intervals.values() for span in spans), flat.length_m)
    if missing:
        stretches = tuple(Stretch(a, b, flat.at(a), flat.at(b)) for a, b in missing)
        count = "a stretch" if len(stretches) == 1 else f"{len(stretches)} stretches"
        return Refused(
            "route",
            f"{count} no station covers: "
            + "; ".join(s.describe() for s in stretches)
            + ". Add a station whose range covers it, or change the route",
            stretches,
            Refusal.UNCOVERED,
        )
    enters = {sid: spans[0][0] for sid, spans in intervals.items() if spans}
    centres = {s.id: north_east_m(route[0], s.location) for s in stations}

    def order(sid: int) -> tuple[float, float, int]:
        north, east = flat.flat_at(enters[sid])
        centre = centres[sid]
        return enters[sid], math.hypot(north - centre[0], east - centre[1]), sid

    ring = tuple(sorted(enters, key=order))
    return Admitted(ring, ring[0], enters, flat.length_m)


def check_submission(
    drone: str, route: Sequence[Position], stations: Sequence[Station]
) -> Refused | None:
    """The first malformed field of a submission, as a ``Refused``; None if none is."""
    if not drone.strip() or drone != drone.strip():
        return Refused("drone", f"{drone!r}: give the drone's name, without surrounding blanks")
    if not route:
        return Refused("route", "empty: give the take-off point first, then the positions flown")
    for k, point in enumerate(route):
        bad = _bad_place(point)
        if bad:
            return Refused(f"route[{k}].{bad[0]}", bad[1])
        if (far := _distance_m(route[0], point)) > MAX_REACH_M:
            return Refused(
                f"route[{k}]",
                f"{far / 1e3:.1f} km from take-off, over {MAX_REACH_M / 1e3:g} km: admission "
                "measures on a flat Earth around take-off; split the mission",
            )
    if not stations:
        return Refused(
            "stations",
            "none registered; add the stations first (baton fleet stations add)",
            kind=Refusal.NO_STATIONS,
        )
    seen: set[int] = set()
    for k, station in enumerate(stations):
        if station.id in seen:
            return Refused(f"stations[{k}].id", f"{station.id} appears twice; give each its own")
        seen.add(station.id)
        problem = station_problem(station)
        if problem is not None:
            return Refused(f"stations[{k}].{problem[0]}", problem[1])
    return None


def station_problem(station: Station) -> tuple[str, str] | None:
    """A station's malformed field (``id``, ``location.latitude_deg``, ``range_m``) and
    what is wrong with it; None if it is well formed."""
    if not 0 <= station.id <= MAX_STATION_ID:
        return "id", f"{station.id}: must be in [0, {MAX_STATION_ID}] (a controller id)"
    bad = _bad_place(station.location)
    if bad:
        return f"location.{bad[0]}", bad[1]
    if not 0 < station.range_m < math.inf:
        return "range_m", f"{station.range_m!r}: must be > 0 and finite, metres"
    return None


def covered_intervals(
    route: Sequence[Position], stations: Sequence[Station]
) -> dict[int, list[tuple[float, float]]]:
    """For each station, the parts of the route in its range, as (from, to) metres
    along the route, in route order (a route that leaves a range and comes back has
    two); a station the route never enters has none."""
    return _covered(FlatRoute.of(route), stations)


@dataclass(frozen=True)
class FlatRoute:
    """A route on the flat Earth around its take-off: its points as (north, east)
    metres, and the metres along the route at each."""

    origin: Position
    points: tuple[tuple[float, float], ...]
    along: tuple[float, ...]

    @classmethod
    def of(cls, route: Sequence[Position]) -> FlatRoute:
        points = tuple(north_east_m(route[0], point) for point in route)
        along = [0.0]
        for (n0, e0), (n1, e1) in itertools.pairwise(points):
            along.append(along[-1] + math.hypot(n1 - n0, e1 - e0))
        return cls(route[0], points, tuple(along))

    @property
    def length_m(self) -> float:
        return self.along[-1]

    def legs(self) -> Iterator[tuple[float, tuple[float, float], tuple[float, float]]]:
        """Each leg as (metres along the route at its start, start, end); a route of
        one point is one leg of no length."""
        if len(self.points) == 1:
            yield 0.0, self.points[0], self.points[0]
        for k in range(len(self.points) - 1):
            yield self.along[k], self.points[k], self.points[k + 1]

    def flat_at(self, at_m: float) -> tuple[float, float]:
        """(north, east) metres of take-off of the point ``at_m`` along the route
        (its ends outside it)."""
        k = min(max(bisect.bisect_left(self.along, at_m), 1), len(self.points) - 1)
        if k == 0:  # a route of one point
            return self.points[0]
        leg = self.along[k] - self.along[k - 1]
        t = 0.0 if leg <= 0 else min(max((at_m - self.along[k - 1]) / leg, 0.0), 1.0)
        (n0, e0), (n1, e1) = self.points[k - 1], self.points[k]
        return n0 + t * (n1 - n0), e0 + t * (e1 - e0)

    def at(self, at_m: float) -> Position:
        """The position ``at_m`` metres along the route."""
        return offset(self.origin, *self.flat_at(at_m))


def _covered(flat: FlatRoute, stations: Sequence[Station]) -> dict[int, list[tuple[float, float]]]:
    spans: dict[int, list[tuple[float, float]]] = {}
    for station in stations:
        centre = north_east_m(flat.origin, station.location)
        found: list[tuple[float, float]] = []
        for along, start, end in flat.legs():
            hit = _leg_in_disc(start, end, centre, station.range_m)
            if hit is not None:
                found.append((along + hit[0], along + hit[1]))
        spans[station.id] = _merged(found)
    return spans


def _bad_place(place: Position) -> tuple[str, str] | None:
    """The field of a latitude or longitude out of bounds, and why; None if both hold."""
    for name, value, bound in (
        ("latitude_deg", place.latitude_deg, 90.0),
        ("longitude_deg", place.longitude_deg, 180.0),
    ):
        if not -bound <= value <= bound:  # nan too
            return name, f"{value!r}: must be a number in [-{bound:g}, {bound:g}], degrees"
    return None


def _distance_m(a: Position, b: Position) -> float:
    north, east = north_east_m(a, b)
    return math.hypot(north, east)


def _leg_in_disc(
    start: tuple[float, float], end: tuple[float, float], centre: tuple[float, float], r: float
) -> tuple[float, float] | None:
    """The part of the straight leg ``start``-``end`` within ``r`` of ``centre``, as
    (from, to) metres from ``start``; None if the leg stays outside."""
    dn, de = end[0] - start[0], end[1] - start[1]
    length = math.hypot(dn, de)
    pn, pe = start[0] - centre[0], start[1] - centre[1]
    c = pn * pn + pe * pe - r * r
    if length <= 0:
        return (0.0, 0.0) if c <= 0 else None
    un, ue = dn / length, de / length
    # |p + t u| = r: t^2 + 2 (p.u) t + c = 0, the leg inside between the roots.
    b = pn * un + pe * ue
    discriminant = b * b - c
    if discriminant < 0:
        return None
    root = math.sqrt(discriminant)
    t0, t1 = max(-b - root, 0.0), min(-b + root, length)
    return (t0, t1) if t0 <= t1 else None


def _merged(spans: Sequence[tuple[float, float]]) -> list[tuple[float, float]]:
    """Sorted intervals with those that overlap or touch made one."""
    merged: list[tuple[float, float]] = []
    for a, b in sorted(spans):
        if merged and a <= merged[-1][1] + TOUCHING_M:
            merged[-1] = (merged[-1][0], max(merged[-1][1], b))
        else:
            merged.append((a, b))
    return merged


def gaps(spans: Sequence[tuple[float, float]], length_m: float) -> list[tuple[float, float]]:
    """The parts of [0, length_m] no span covers."""
    if not spans:
        return [(0.0, length_m)]
    found: list[tuple[float, float]] = []
    reached = 0.0
    for a, b in _merged(spans):
        if a > reached + TOUCHING_M:
            found.append((reached, a))
        reached = max(reached, b)
    if reached < length_m - TOUCHING_M:
        found.append((reached, length_m))
    return found
