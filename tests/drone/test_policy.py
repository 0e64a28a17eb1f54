"""The handover policy as a pure function of positions, velocities, ranges and link states."""

from __future__ import annotations

import math

import pytest

from baton.drone.policy import (
    FLY_ON,
    HANDOVER,
    HOLD,
    STAY,
    Decision,
    Fix,
    LinkBounds,
    LinkState,
    PolicyParams,
    PolicyState,
    Station,
    decide,
    distance_m,
    entry_m,
    link_problem,
    time_in_range_s,
)
from baton.sdk import Position, offset

ORIGIN = Position(47.397742, 8.545594)
UP = LinkState(up=True)


def at(east_m: float, north_m: float = 0.0) -> Position:
    return offset(ORIGIN, north_m, east_m)


def stations(*placed: tuple[float, float]) -> dict[int, Station]:
    """Stations 0, 1, ... at (east metres, range metres) along a line through ORIGIN."""
    return {k: Station(k, at(east), rng) for k, (east, rng) in enumerate(placed)}


def fix(
    east_m: float, east_m_s: float = 0.0, north_m: float = 0.0, leg_to: float | None = None
) -> Fix:
    """The vehicle ``east_m`` east (and ``north_m`` north), flying a leg to ``leg_to`` east."""
    leg = None if leg_to is None else at(leg_to)
    return Fix(at(east_m, north_m), north_m_s=0.0, east_m_s=east_m_s, leg_to=leg)


def run(
    params: PolicyParams,
    placed: dict[int, Station],
    track: list[tuple[float, Fix]],
    master: int = 0,
    links: dict[int, LinkState] | None = None,
) -> tuple[list[tuple[float, Decision]], int]:
    """Feeds a track of (mission time, fix) through the policy, switching masters as it
    says (as the drone does); returns every handover or hold and the final master."""
    state = PolicyState()
    links = links or {cid: UP for cid in placed}
    events = []
    for now, where in track:
        decision, state = decide(params, placed, where, links, master, state, now)
        if decision.action == HANDOVER:
            assert decision.target is not None and decision.target != master
            master = decision.target
        if decision.action != STAY:
            events.append((now, decision))
    return events, master


NEAREST = PolicyParams("nearest", margin_m=50.0, dwell_s=2.0)
PREDICTIVE = PolicyParams("predictive", lead_s=10.0)


# -- geometry ---------------------------------------------------------------------------


def test_exactly_on_the_circle_is_in_range_and_just_beyond_is_not() -> None:
    where = fix(300.0, north_m=400.0)
    # 500 m, to the last bit of the float, as the policy measures it.
    radius = distance_m(Station(0, ORIGIN, 1.0), where)
    on = {0: Station(0, ORIGIN, radius), 1: Station(1, at(2000.0), 100.0)}
    decision, _ = decide(NEAREST, on, where, {0: UP, 1: UP}, 0, PolicyState(), 0.0)
    assert decision.action == STAY, decision
    beyond = {0: Station(0, ORIGIN, radius * (1 - 1e-9)), 1: on[1]}
    decision, _ = decide(NEAREST, beyond, where, {0: UP, 1: UP}, 0, PolicyState(), 0.0)
    assert decision.action == HOLD and "0 out of range" in decision.reason


def test_time_in_range_follows_the_track() -> None:
    station = Station(0, ORIGIN, 500.0)
    assert time_in_range_s(fix(100.0, east_m_s=10.0), station) == pytest.approx(40.0)
    assert time_in_range_s(fix(100.0, east_m_s=-10.0), station) == pytest.approx(60.0)
    assert time_in_range_s(fix(100.0), station) == math.inf
    assert time_in_range_s(fix(600.0, east_m_s=-10.0), station) == 0.0
    # Across the circle off-centre: a chord, not the distance to the edge.
    sideways = Fix(at(0.0, north_m=300.0), north_m_s=0.0, east_m_s=10.0)
    assert time_in_range_s(sideways, station) == pytest.approx(40.0)


def test_where_a_leg_enters_a_range() -> None:
    station = Station(0, at(1000.0), 300.0)
    assert entry_m(fix(0.0, leg_to=1500.0), station) == pytest.approx(700.0)
    assert entry_m(fix(0.0, leg_to=700.0), station) == pytest.approx(700.0)  # on the circle
    assert entry_m(fix(0.0, leg_to=690.0), station) is None  # ends short of it
    assert entry_m(fix(1500.0, leg_to=0.0), station) == pytest.approx(200.0)  # from the east
    assert entry_m(fix(0.0, leg_to=-500.0), station) is None  # flying away
    assert entry_m(fix(0.0), station) is None  # no leg known
    assert entry_m(fix(900.0), station) == 0.0  # in it, leg or not
    # Passing north of the station: in at 300 m off its line only if the leg comes
    # within 300 m.
    assert entry_m(fix(0.0, north_m=299.0, leg_to=None), station) is None
    skim = Fix(at(0.0, north_m=299.0), leg_to=at(2000.0, north_m=299.0))
    assert entry_m(skim, station) == pytest.approx(1000.0 - math.sqrt(300**2 - 299**2), abs=0.5)
    wide = Fix(at(0.0, north_m=301.0), leg_to=at(2000.0, north_m=301.0))
    assert entry_m(wide, station) is None


def test_bad_parameters_are_named() -> None:
    with pytest.raises(ValueError, match="unknown handover policy 'closest'"):
        PolicyParams("closest")
    with pytest.raises(ValueError, match="margin_m must be >= 0"):
        PolicyParams("nearest", margin_m=-1.0)


# -- nearest ----------------------------------------------------------------------------


def test_nearest_waits_for_the_margin_and_the_dwell() -> None:
    placed = stations((0.0, 600.0), (1000.0, 600.0))
    state = PolicyState()
    # 20 m past the midpoint: nearer, but not by the margin.
    decision, state = decide(NEAREST, placed, fix(520.0), {0: UP, 1: UP}, 0, state, 0.0)
    assert decision.action == STAY and "no usable station nearer by 50 m" in decision.reason
    # 40 m past: nearer by 80 m; the dwell starts.
    decision, state = decide(NEAREST, placed, fix(540.0), {0: UP, 1: UP}, 0, state, 1.0)
    assert decision.action == STAY and "for 0.0 s of 2 s" in decision.reason
    decision, state = decide(NEAREST, placed, fix(545.0), {0: UP, 1: UP}, 0, state, 2.5)
    assert decision.action == STAY
    decision, state = decide(NEAREST, placed, fix(550.0), {0: UP, 1: UP}, 0, state, 3.0)
    assert decision == Decision(HANDOVER, decision.reason, target=1)
    assert "1 nearer (450 m) than master 0 (550 m of 600 m)" in decision.reason


def test_a_nearest_handover_stands_until_the_master_has_moved() -> None:
    """A prepared handover takes its time (under load, longer than the dwell): while
    the master has not moved, the next decision is the same handover, not a new dwell
    and a second decision (the corridor testbed counted two for one crossing)."""
    placed = stations((0.0, 600.0), (1000.0, 600.0))
    state = PolicyState()
    decision, state = decide(NEAREST, placed, fix(540.0), {0: UP, 1: UP}, 0, state, 1.0)
    decision, state = decide(NEAREST, placed, fix(550.0), {0: UP, 1: UP}, 0, state, 3.0)
    assert decision.action == HANDOVER and decision.target == 1
    for now in (3.1, 3.5, 4.0):
        again, state = decide(NEAREST, placed, fix(551.0), {0: UP, 1: UP}, 0, state, now)
        assert (again.action, again.target) == (HANDOVER, 1), again.reason
    # Moved: the candidate was the new master, forgotten; the margin counts from 1 now.
    decision, state = decide(NEAREST, placed, fix(552.0), {0: UP, 1: UP}, 1, state, 4.1)
    assert decision.action == STAY and state.candidate is None


def test_overlapping_ranges_pick_the_nearest_usable() -> None:
    # Three overlapping stations; the nearest (2) has its link down, so 1 it is.
    placed = stations((0.0, 1000.0), (700.0, 1000.0), (900.0, 1000.0))
    links = {0: UP, 1: UP, 2: LinkState(up=False, down_for_s=10.0)}
    track = [(t * 0.5, fix(880.0)) for t in range(10)]
    events, master = run(NEAREST, placed, track, links=links)
    assert master == 1 and len(events) == 1
    # Master 0 out of range: at once, no dwell, to the nearest usable.
    events, master = run(NEAREST, placed, [(0.0, fix(1050.0))], links={c: UP for c in placed})
    assert master == 2 and "master 0 out of range (1050 m of 1000 m)" in events[0][1].reason


def test_no_station_in_range_holds_and_goes_on_when_one_is() -> None:
    placed = stations((0.0, 300.0), (1000.0, 300.0))
    track = [(0.0, fix(350.0)), (1.0, fix(500.0)), (2.0, fix(710.0))]
    events, master = run(NEAREST, placed, track)
    [hold, hold_again, moved] = [decision for _, decision in events]
    assert hold.action == HOLD and hold_again.action == HOLD
    assert hold.reason == (
        "no controller usable: 0 out of range (350 m of 300 m); 1 out of range (650 m of 300 m)"
    )
    assert moved.action == HANDOVER and moved.target == 1 and master == 1
    assert moved.takeover is False  # 0's link is still up: it can be told


def test_none_usable_flies_on_along_a_leg_into_a_range_else_holds() -> None:
    # Master 0 lost in its range only (a gap from 300 to 500 m east); the leg goes on.
    placed = stations((0.0, 400.0), (900.0, 400.0), (1600.0, 400.0))
    lost = {0: LinkState(up=False, down_for_s=5.0), 1: LinkState(up=False, down_for_s=60.0)}
    # A leg to 1200 m: into 1's range at 500 m (and 2's at 1200 m, later). The
    # velocity gives the time.
    decision, state = decide(
        NEAREST, placed, fix(300.0, east_m_s=5.0, leg_to=1200.0), lost, 0, PolicyState(), 0.0
    )
    assert (decision.action, decision.target) == (FLY_ON, 1)
    assert decision.reason == (
        "no controller usable: 0 link down (5.0 s, 300 m of 400 m); 1 out of range "
        "(600 m of 400 m); 2 out of range (1300 m of 400 m); flying on: the leg "
        "enters 1's range in 200 m, 40 s"
    )
    assert state.entered == ((0, -math.inf),)
    # A leg ending in the gap, or no leg known: hold.
    decision, _ = decide(NEAREST, placed, fix(300.0, leg_to=450.0), lost, 0, PolicyState(), 0.0)
    assert decision.action == HOLD
    assert decision.reason.endswith("; the leg leads into no station's range")
    decision, _ = decide(NEAREST, placed, fix(300.0), lost, 0, PolicyState(), 0.0)
    assert decision.action == HOLD and decision.reason.endswith("2 out of range (1300 m of 400 m)")
    # Back into the dead master's range is no way out: it was waited out already.
    decision, _ = decide(NEAREST, placed, fix(300.0, leg_to=0.0), lost, 0, PolicyState(), 0.0)
    assert decision.action == HOLD


def test_flown_into_a_range_its_link_has_link_up_s_to_come_up() -> None:
    placed = stations((0.0, 400.0), (900.0, 400.0))
    params = PolicyParams("nearest", link_up_s=20.0)
    lost = {0: LinkState(up=False, down_for_s=5.0), 1: LinkState(up=False, down_for_s=60.0)}
    track = [(float(t), fix(300.0 + 10.0 * t, east_m_s=10.0, leg_to=1200.0)) for t in range(50)]
    events, master = run(params, placed, track, links=lost)
    # Flying on to 1's range (entered at t = 20 s), then 20 s for 1's link; no link:
    # hold at t = 40 s, and again while nothing changes.
    assert {d.action for t, d in events if t < 40} == {FLY_ON}
    assert "in 1's range (400 m of 400 m), its link has 20.0 s more" in events[20][1].reason
    assert "its link has 1.0 s more" in events[39][1].reason
    assert {d.action for t, d in events if t >= 40} == {HOLD} and master == 0
    # Its link up within the time: taken over (0 cannot be told), no hold.
    state = PolicyState()
    for now, where in track[:30]:
        decision, state = decide(params, placed, where, lost, 0, state, now)
    assert decision.action == FLY_ON
    up = {**lost, 1: UP}
    decision, state = decide(params, placed, fix(600.0, leg_to=1200.0), up, 0, state, 30.0)
    assert (decision.action, decision.target, decision.takeover) == (HANDOVER, 1, True)
    assert state == PolicyState(entered=((1, 20.0),))


def test_a_station_whose_range_holds_the_vehicle_long_enough_is_not_flown_on_for() -> None:
    # The vehicle has been in 1's range for 30 s (and 0's) when master 0's link is
    # lost: 1's link is down as well, so it does not answer here; no way out.
    placed = stations((0.0, 400.0), (500.0, 400.0))
    state = PolicyState(entered=((0, 0.0), (1, 0.0)))
    lost = {0: LinkState(up=False, down_for_s=5.0), 1: LinkState(up=False, down_for_s=0.5)}
    leg = fix(300.0, leg_to=600.0)
    decision, state = decide(NEAREST, placed, leg, lost, 0, state, 30.0)
    assert decision.action == HOLD and "1 link down (0.5 s, 200 m of 400 m)" in decision.reason
    assert state.entered == ((0, 0.0), (1, 0.0))
    # Entered 5 s ago: flown on for (its link may be coming up).
    state = PolicyState(entered=((0, 0.0), (1, 25.0)))
    decision, state = decide(NEAREST, placed, leg, lost, 0, state, 30.0)
    assert (decision.action, decision.target) == (FLY_ON, 1)
    assert "in 1's range (200 m of 400 m), its link has 15.0 s more" in decision.reason
    # Out of range forgets it; back in, it counts from then.
    _, state = decide(NEAREST, placed, fix(1000.0), lost, 0, state, 31.0)
    assert state.entered == ()


def test_out_of_range_stations_and_dead_links_are_never_chosen() -> None:
    # 1 is nearest but out of range; 2 in range but its link is down; 3 too slow.
    placed = stations((0.0, 100.0), (400.0, 50.0), (500.0, 400.0), (600.0, 400.0))
    links = {
        0: UP,
        1: UP,
        2: LinkState(up=False, down_for_s=1.0),
        3: LinkState(up=True, rtt_s=2.5),
    }
    decision, _ = decide(NEAREST, placed, fix(300.0), links, 0, PolicyState(), 0.0)
    assert decision.action == HOLD
    assert "1 out of range" in decision.reason and "2 link down" in decision.reason
    assert "3 link too slow (round trip 2.50 s over 2 s)" in decision.reason


BOUNDS = LinkBounds(max_rtt_s=0.5, rtt_stale_s=3.0)


def test_link_health_is_up_with_a_round_trip_fast_and_fresh_enough() -> None:
    # Nothing measured yet (a stream just opened): healthy.
    assert link_problem(UP, BOUNDS) == ""
    assert link_problem(LinkState(up=True, rtt_s=0.5, rtt_age_s=3.0), BOUNDS) == ""
    assert link_problem(LinkState(up=True, rtt_s=0.51, rtt_age_s=0.1), BOUNDS) == (
        "link too slow (round trip 0.51 s over 0.5 s)"
    )
    assert link_problem(LinkState(up=True, rtt_s=0.01, rtt_age_s=3.2), BOUNDS) == (
        "link stale (last round trip 3.2 s ago, over 3 s)"
    )
    # Pings sent, none answered: judged by the first one's age.
    assert link_problem(LinkState(up=True, rtt_age_s=2.9), BOUNDS) == ""
    assert link_problem(LinkState(up=True, rtt_age_s=3.5), BOUNDS) == (
        "link silent (no answer to a ping of 3.5 s ago)"
    )
    # Down says so, whatever was measured before.
    down = LinkState(up=False, down_for_s=1.5, rtt_s=0.01, rtt_age_s=0.2)
    assert link_problem(down, BOUNDS) == "link down (1.5 s)"


def test_a_slow_or_stale_link_is_not_chosen_and_a_master_on_one_is_left() -> None:
    bounds = LinkBounds(max_rtt_s=0.3, rtt_stale_s=2.0)
    params = PolicyParams("nearest", margin_m=50.0, dwell_s=0.0, link_bounds=bounds)
    placed = stations((0.0, 600.0), (500.0, 600.0), (600.0, 600.0))
    fast = LinkState(up=True, rtt_s=0.01, rtt_age_s=0.5)
    slow = LinkState(up=True, rtt_s=0.8, rtt_age_s=0.5)
    stale = LinkState(up=True, rtt_s=0.01, rtt_age_s=2.5)
    # 1 and 2 nearer than master 0 by far, but 1 slow: the drone goes to 2.
    links = {0: fast, 1: slow, 2: fast}
    decision, _ = decide(params, placed, fix(450.0), links, 0, PolicyState(), 0.0)
    assert (decision.action, decision.target) == (HANDOVER, 2), decision
    # Both slow or stale: the master stays.
    links = {0: fast, 1: slow, 2: stale}
    decision, _ = decide(params, placed, fix(450.0), links, 0, PolicyState(), 0.0)
    assert decision.action == STAY and "no usable station nearer" in decision.reason
    # The master's link slow: the nearest usable takes over at once, told (its
    # stream is up: a cooperative handover, not a takeover).
    links = {0: slow, 1: fast, 2: fast}
    decision, _ = decide(params, placed, fix(100.0), links, 0, PolicyState(), 0.0)
    assert (decision.action, decision.target, decision.takeover) == (HANDOVER, 1, False)
    assert decision.reason.startswith("master 0 link too slow (round trip 0.80 s over 0.3 s)")
    # A master chosen by the operator is left too when its link goes stale.
    links = {0: stale, 1: fast, 2: fast}
    decision, _ = decide(params, placed, fix(100.0), links, 0, PolicyState(pinned=0), 0.0)
    assert (decision.action, decision.target) == (HANDOVER, 1)
    assert "master 0 link stale (last round trip 2.5 s ago, over 2 s)" in decision.reason


def test_the_masters_link_lost_in_range_is_waited_out_then_taken_over() -> None:
    placed = stations((0.0, 600.0), (800.0, 600.0))
    for down in (0.5, 2.9):
        links = {0: LinkState(up=False, down_for_s=down), 1: UP}
        decision, _ = decide(NEAREST, placed, fix(300.0), links, 0, PolicyState(), 0.0)
        assert decision.action == STAY and "waiting 3 s" in decision.reason
        assert decision.waiting  # nobody commands the vehicle: a held one is not resumed
    links = {0: LinkState(up=False, down_for_s=3.0), 1: UP}
    decision, _ = decide(NEAREST, placed, fix(300.0), links, 0, PolicyState(), 0.0)
    assert decision.action == HANDOVER and decision.target == 1 and decision.takeover
    assert decision.reason.startswith("master 0 link down (3.0 s, 300 m of 600 m)")
    # And nobody else usable: hold.
    far = stations((0.0, 600.0), (2000.0, 600.0))
    decision, _ = decide(NEAREST, far, fix(300.0), links, 0, PolicyState(), 0.0)
    assert decision.action == HOLD


def test_back_and_forth_across_a_boundary_one_handover_per_crossing() -> None:
    placed = stations((0.0, 700.0), (1000.0, 700.0))
    track: list[tuple[float, Fix]] = []
    # Up to the midpoint, dither across it within the margin, then cross for good;
    # three crossings.
    for start, end in [(300, 700), (700, 300), (300, 700)]:
        step = 10 if end > start else -10
        path = [*range(start, 500, step), *[500 + w for w in [10, -15, 20, -20, 15, -10] * 3]]
        path += range(500, end, step)
        track += [(0.0, fix(float(east))) for east in path]
    track = [(0.5 * k, where) for k, (_, where) in enumerate(track)]
    events, master = run(NEAREST, placed, track)
    assert [d.target for _, d in events] == [1, 0, 1]
    assert master == 1


def test_back_and_forth_on_the_edge_of_range_does_not_flap() -> None:
    # The vehicle hovers around 0's range edge where 1 is barely nearer.
    placed = stations((0.0, 500.0), (1040.0, 600.0))
    track = [(k * 0.5, fix(500.0 + (10 if k % 2 else -10))) for k in range(40)]
    events, _ = run(NEAREST, placed, track)
    # Out of 0's range at 510 m: handed to 1 once, and 1 stays (in range, 0 not nearer by 50 m).
    assert [d.target for _, d in events] == [1]


def test_a_pinned_master_is_kept_while_usable() -> None:
    placed = stations((0.0, 600.0), (1000.0, 600.0))
    state = PolicyState().pin(0)
    for now, east in enumerate([560.0, 580.0, 590.0, 595.0]):
        decision, state = decide(NEAREST, placed, fix(east), {0: UP, 1: UP}, 0, state, now)
        assert decision.action == STAY and "chosen by the script or operator" in decision.reason
    decision, state = decide(NEAREST, placed, fix(610.0), {0: UP, 1: UP}, 0, state, 9.0)
    assert decision.action == HANDOVER and decision.target == 1 and state.pinned is None


# -- predictive -------------------------------------------------------------------------


def test_predictive_hands_over_before_the_range_runs_out() -> None:
    placed = stations((0.0, 500.0), (500.0, 500.0), (1000.0, 500.0))
    track: list[tuple[float, Fix]] = [
        (t, fix(10.0 * t + 5.0, east_m_s=10.0)) for t in range(0, 150)
    ]
    events, master = run(PREDICTIVE, placed, track)
    # At 10 m/s with a 10 s lead: the first fix less than 100 m before each edge
    # (405 m, 905 m).
    assert [(t, d.target) for t, d in events] == [(40.0, 1), (90.0, 2)]
    assert "master 0's range runs out in 9.5 s; 1 keeps the vehicle" in events[0][1].reason
    assert master == 2


def test_predictive_picks_the_station_the_vehicle_stays_in_longest() -> None:
    # 1 is nearer, but the vehicle flies away from it; 2 lies ahead.
    placed = stations((0.0, 500.0), (300.0, 300.0), (900.0, 600.0))
    decision, _ = decide(
        PREDICTIVE, placed, fix(420.0, east_m_s=10.0), {0: UP, 1: UP, 2: UP}, 0, PolicyState(), 0
    )
    assert decision.action == HANDOVER and decision.target == 2
    assert "2 keeps the vehicle in range longest (108.0 s, 480 m of 600 m)" in decision.reason


def test_predictive_stays_when_still_or_when_nobody_lasts_longer() -> None:
    placed = stations((0.0, 500.0), (800.0, 310.0))
    links = {0: UP, 1: UP}
    decision, _ = decide(PREDICTIVE, placed, fix(480.0), links, 0, PolicyState(), 0.0)
    assert decision.action == STAY and "while it is still" in decision.reason
    # Flying north across the overlap: 1's range ends before 0's.
    across = Fix(at(495.0, north_m=-20.0), north_m_s=10.0, east_m_s=0.0)
    decision, _ = decide(PREDICTIVE, placed, across, links, 0, PolicyState(), 0.0)
    assert decision.action == STAY and "no usable station keeps" in decision.reason


def test_predictive_back_and_forth_over_the_overlap_hands_over_once_per_crossing() -> None:
    placed = stations((0.0, 500.0), (600.0, 500.0))
    track: list[tuple[float, Fix]] = []
    now = 0.0
    # Between 250 and 350 m (both ranges, over 10 s from either edge)...
    for _ in range(4):
        for east in range(250, 350, 10):
            track.append((now, fix(float(east), east_m_s=10.0)))
            now += 1.0
        for east in range(350, 250, -10):
            track.append((now, fix(float(east), east_m_s=-10.0)))
            now += 1.0
    events, _ = run(PREDICTIVE, placed, track)
    assert events == []
    # ... then out of 0's range and back in, twice: one handover, to 1, on the way out.
    for _ in range(2):
        for east in range(250, 560, 10):
            track.append((now, fix(float(east), east_m_s=10.0)))
            now += 1.0
        for east in range(560, 250, -10):
            track.append((now, fix(float(east), east_m_s=-10.0)))
            now += 1.0
    events, master = run(PREDICTIVE, placed, track)
    assert [d.target for _, d in events] == [1] and master == 1


def test_a_handover_decision_under_the_lock_does_what_the_master_can() -> None:
    """``handover_step``: the one rule the drone's policy runner and the simulation's
    carry out once they hold the execution lock."""
    from baton.drone.policy import (
        ALREADY_PREPARING,
        HANDOVER,
        HOLD,
        MOVED,
        PREPARE,
        STAY,
        SWITCH,
        Decision,
        handover_step,
        hold_due,
        resume_due,
    )

    to_2 = Decision(HANDOVER, "range runs out", target=2)
    assert handover_step(to_2, 1, 3, True, None) == MOVED
    assert handover_step(to_2, 1, 1, False, None) == SWITCH  # no Connect stream to prepare on
    taking = Decision(HANDOVER, "master lost", target=2, takeover=True)
    assert handover_step(taking, 1, 1, True, None) == SWITCH
    assert handover_step(to_2, 1, 1, True, 2) == ALREADY_PREPARING
    assert handover_step(to_2, 1, 1, True, 3) == PREPARE
    hold = Decision(HOLD, "none usable")
    assert hold_due(hold, holding=False) and not hold_due(hold, holding=True)
    assert hold_due(hold, holding=True, unsure=True)  # a restarted drone commands it again
    assert resume_due(Decision(STAY, "ok"), holding=True)
    assert not resume_due(Decision(STAY, "ok"), holding=False)
    assert not resume_due(hold, holding=True)
