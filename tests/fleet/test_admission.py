"""The admission rule's corners: which stations cover a route, the ring, the first
master, and what is refused."""

from __future__ import annotations

import math

import pytest

from baton.drone.policy import Station
from baton.fleet.admission import Admitted, Refused, admit_mission, covered_intervals
from baton.sdk import Position, offset

HOME = Position(47.397742, 8.545594)


def at(north_m: float, east_m: float) -> Position:
    return offset(HOME, north_m, east_m)


def station(sid: int, north_m: float, east_m: float, range_m: float) -> Station:
    return Station(sid, at(north_m, east_m), range_m)


def admitted(result: Admitted | Refused) -> Admitted:
    assert isinstance(result, Admitted), result
    return result


def refused(result: Admitted | Refused) -> Refused:
    assert isinstance(result, Refused), result
    return result


def test_a_single_station_covering_the_route_is_the_ring_and_the_master() -> None:
    result = admitted(admit_mission("d1", [at(0, 0), at(0, 300)], [station(7, 0, 100, 500)], {}))
    assert result.ring == (7,) and result.first_master == 7
    assert result.length_m == pytest.approx(300, abs=0.01)


def test_a_gap_between_two_ranges_is_refused_naming_the_stretch() -> None:
    # Ranges end at 400 m and start again at 600 m east of take-off.
    stations = [station(0, 0, 0, 400), station(1, 0, 1000, 400)]
    result = refused(admit_mission("d1", [at(0, 0), at(0, 1000)], stations, {}))
    assert result.field == "route"
    [gap] = result.uncovered
    assert gap.from_m == pytest.approx(400, abs=0.01)
    assert gap.to_m == pytest.approx(600, abs=0.01)
    start = at(0, 400)
    assert gap.start.latitude_deg == pytest.approx(start.latitude_deg, abs=1e-7)
    assert gap.start.longitude_deg == pytest.approx(start.longitude_deg, abs=1e-7)
    assert "at 400 m along the route to" in result.message()
    assert "at 600 m (200 m)" in result.message()


def test_a_gap_narrower_than_any_sampling_step_is_found() -> None:
    # Two ranges 10 cm apart on the route: exact intervals, no step to miss it.
    stations = [station(0, 0, 0, 400), station(1, 0, 800.1, 400)]
    result = refused(admit_mission("d1", [at(0, 0), at(0, 800)], stations, {}))
    [gap] = result.uncovered
    assert gap.to_m - gap.from_m == pytest.approx(0.1, abs=0.01)


def test_ranges_that_touch_on_the_route_cover_it() -> None:
    # On the circle is in range, as for the handover policy.
    stations = [station(0, 0, 0, 400), station(1, 0, 800, 400)]
    assert admitted(admit_mission("d1", [at(0, 0), at(0, 800)], stations, {})).ring == (0, 1)


def test_uncovered_take_off_and_end_are_stretches_too() -> None:
    result = refused(admit_mission("d1", [at(0, 0), at(0, 1000)], [station(0, 0, 500, 300)], {}))
    assert [(round(g.from_m), round(g.to_m)) for g in result.uncovered] == [(0, 200), (800, 1000)]


def test_a_route_that_leaves_and_reenters_a_range_keeps_its_first_entry() -> None:
    # Out east through 0 then 1, back west through 0: station 0 twice, ring [0, 1].
    stations = [station(0, 0, 0, 300), station(1, 0, 600, 300)]
    route = [at(0, 0), at(0, 900), at(0, 0)]
    spans = covered_intervals(route, stations)
    assert [(round(a), round(b)) for a, b in spans[0]] == [(0, 300), (1500, 1800)]
    result = admitted(admit_mission("d1", route, stations, {}))
    assert result.ring == (0, 1) and result.enters_at_m[1] == pytest.approx(300, abs=0.01)


def test_the_ring_is_in_the_order_the_route_first_enters_each_range() -> None:
    # Listed out of order; a station the route never enters is left out.
    stations = [
        station(3, 0, 1200, 400),
        station(1, 0, 500, 400),
        station(9, 5000, 0, 400),
        station(0, 0, 0, 400),
    ]
    result = admitted(admit_mission("d1", [at(0, 0), at(0, 1500)], stations, {}))
    assert result.ring == (0, 1, 3) and result.first_master == 0


def test_the_first_master_is_the_nearest_station_whose_range_holds_take_off() -> None:
    # Station 1 is nearer take-off but does not reach it; 2 holds it, 0 is farther.
    stations = [station(0, 0, -300, 400), station(1, 0, 30, 20), station(2, 0, 100, 200)]
    result = admitted(admit_mission("d1", [at(0, 0), at(0, 100)], stations, {}))
    assert result.first_master == 2
    assert result.ring == (2, 0, 1)


def test_ties_go_to_the_lower_id() -> None:
    # Two stations as far from take-off, and entered at the same point.
    stations = [station(5, 100, 0, 500), station(2, -100, 0, 500)]
    result = admitted(admit_mission("d1", [at(0, 0), at(0, 200)], stations, {}))
    assert result.ring == (2, 5) and result.first_master == 2


def test_a_drone_already_flying_a_mission_is_refused() -> None:
    result = refused(admit_mission("d1", [at(0, 0)], [station(0, 0, 0, 100)], {"d1": 4}))
    assert result.field == "drone" and "already flies mission 4" in result.reason
    assert isinstance(admit_mission("d2", [at(0, 0)], [station(0, 0, 0, 100)], {"d1": 4}), Admitted)


@pytest.mark.parametrize(
    ("drone", "route", "stations", "field"),
    [
        ("", [HOME], [Station(0, HOME, 10)], "drone"),
        (" d1", [HOME], [Station(0, HOME, 10)], "drone"),
        ("d1", [], [Station(0, HOME, 10)], "route"),
        ("d1", [HOME, Position(95.0, 8.5)], [Station(0, HOME, 10)], "route[1].latitude_deg"),
        ("d1", [HOME, Position(47.4, math.nan)], [Station(0, HOME, 10)], "route[1].longitude_deg"),
        ("d1", [HOME, Position(48.0, 8.5)], [Station(0, HOME, 10)], "route[1]"),
        ("d1", [HOME], [], "stations"),
        ("d1", [HOME], [Station(0, HOME, 10), Station(0, HOME, 20)], "stations[1].id"),
        ("d1", [HOME], [Station(0, HOME, 0)], "stations[0].range_m"),
        ("d1", [HOME], [Station(0, HOME, math.inf)], "stations[0].range_m"),
        ("d1", [HOME], [Station(-1, HOME, 10)], "stations[0].id"),
        ("d1", [HOME], [Station(0, Position(0, 200), 10)], "stations[0].location.longitude_deg"),
    ],
)
def test_a_malformed_submission_is_refused_naming_the_field(
    drone: str, route: list[Position], stations: list[Station], field: str
) -> None:
    result = refused(admit_mission(drone, route, stations, {}))
    assert result.field == field, result
    assert result.message().startswith(f"{field}: ")


def test_a_route_of_one_point_is_a_take_off_to_cover() -> None:
    assert admitted(admit_mission("d1", [HOME], [Station(0, HOME, 10)], {})).ring == (0,)
    far = refused(admit_mission("d1", [HOME], [station(0, 0, 100, 10)], {}))
    assert [(g.from_m, g.to_m) for g in far.uncovered] == [(0.0, 0.0)]
