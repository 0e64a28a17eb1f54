"""The drain rule's corners: which rings can do without a station, from where the
drone is along its route, and where a master on it goes."""

from __future__ import annotations

import pytest

from baton.drone.policy import Station
from baton.fleet.draining import (
    Leave,
    MissionView,
    Stay,
    drain_mission,
    handover_target,
    remaining_route,
)
from baton.sdk import Position, offset

HOME = Position(47.397742, 8.545594)


def at(north_m: float, east_m: float) -> Position:
    return offset(HOME, north_m, east_m)


# Three stations along a 1 km corridor east: 1 at take-off, 2 in the middle, 3 at the
# end; 2 overlaps both, so 1 and 3 alone leave [300, 700] m uncovered.
STATIONS = {
    1: Station(1, at(0, 0), 350),
    2: Station(2, at(0, 500), 450),
    3: Station(3, at(0, 1000), 350),
}
ROUTE = (at(0, 0), at(0, 1000))


def view(
    ring: tuple[int, ...] = (1, 2, 3),
    master: int | None = 1,
    drone_at: Position | None = None,
    route: tuple[Position, ...] = ROUTE,
) -> MissionView:
    return MissionView(7, ring, route, STATIONS, master, drone_at)


def test_a_station_covering_nothing_only_it_covers_leaves_and_its_master_moves_on() -> None:
    # Station 1 covers [0, 350]; 2 covers [50, 950]: from 100 m on 1 is not needed.
    assert drain_mission(1, view(drone_at=at(0, 100))) == Leave(7, hand_over_to=2)
    # A replica leaves without a handover; one still needed stays.
    assert drain_mission(1, view(master=2, drone_at=at(0, 100))) == Leave(7, hand_over_to=None)
    # Station 3 alone covers the last 50 m.
    stay = drain_mission(3, view(master=1, drone_at=at(0, 100)))
    assert isinstance(stay, Stay) and stay.mission_id == 7
    assert stay.reason.startswith("only station 3 of its ring covers the route from (47.397742, ")
    assert "at 950 m to (47.397742, " in stay.reason
    assert stay.reason.endswith(
        "at 1000 m along it, still to fly; drain again once the drone is past it"
    )


def test_a_station_that_alone_covers_what_is_left_to_fly_stays_until_the_drone_is_past() -> None:
    stay = drain_mission(2, view(master=2, drone_at=at(0, 200)))
    assert isinstance(stay, Stay)
    assert "only station 2 of its ring covers the route from" in stay.reason
    assert "at 350 m" in stay.reason and "at 650 m along it" in stay.reason
    # Past the stretch only it covers, it may go; the master moves to the next station
    # in ring order whose range holds the drone.
    assert drain_mission(2, view(master=2, drone_at=at(0, 700))) == Leave(7, hand_over_to=3)


def test_an_unknown_or_off_route_drone_counts_the_whole_route() -> None:
    assert isinstance(drain_mission(1, view(drone_at=None)), Stay)
    assert isinstance(drain_mission(3, view(drone_at=at(0, 970))), Stay)
    # 200 m north of its route: where it is along it is unknown.
    off = drain_mission(1, view(drone_at=at(200, 600)))
    assert isinstance(off, Stay) and "at 0 m to" in off.reason


def test_a_drone_in_no_other_stations_range_keeps_the_station() -> None:
    stay = drain_mission(1, view(drone_at=at(0, 20)))
    assert isinstance(stay, Stay) and "in no other station's range" in stay.reason


def test_a_ring_never_falls_below_two() -> None:
    stay = drain_mission(1, view(ring=(1, 2), drone_at=at(0, 400)))
    assert isinstance(stay, Stay)
    assert "would keep 1 station, fewer than 2 (a master and a replica)" in stay.reason
    with pytest.raises(ValueError, match="not in mission 7's ring"):
        drain_mission(3, view(ring=(1, 2)))


def test_the_handover_target_is_the_next_covering_the_drone_or_the_rings_next() -> None:
    ring = (3, 1, 2)
    assert handover_target(3, ring, STATIONS, at(0, 0)) == 1
    assert handover_target(3, ring, STATIONS, at(0, 600)) == 2  # 1 does not hold it
    assert handover_target(3, ring, STATIONS, None) == 1
    assert handover_target(2, ring, STATIONS, at(500, 0)) == 3  # none holds it: the next
    assert handover_target(2, ring, STATIONS, at(0, 900)) == 3  # wraps around
    # A station drained already (it stays in rings that need it) comes after the
    # others that hold the drone, never before one that holds it.
    assert handover_target(3, ring, STATIONS, at(0, 300)) == 1
    assert handover_target(3, ring, STATIONS, at(0, 300), frozenset({1})) == 2
    assert handover_target(3, ring, STATIONS, at(0, 0), frozenset({1})) == 1
    assert handover_target(3, ring, STATIONS, None, frozenset({1})) == 2


def test_the_remaining_route_starts_at_the_earliest_nearest_leg() -> None:
    there_and_back = (at(0, 0), at(0, 600), at(0, 0), at(0, 900))
    remaining, from_m = remaining_route(there_and_back, at(0, 300))
    # On the first leg (the return leg passes as near): the return is still to fly.
    assert from_m == pytest.approx(300, abs=0.01)
    assert len(remaining) == 4
    remaining, from_m = remaining_route(there_and_back, at(0, 800))
    assert from_m == pytest.approx(2000, abs=0.01) and len(remaining) == 2
    assert remaining_route(there_and_back, None) == (there_and_back, 0.0)
