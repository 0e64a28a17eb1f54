"""``StallWatch`` and the judges: a condition is shown after its threshold, judged
expected or needing a person, and only the latter is logged."""

from __future__ import annotations

from baton.stalls import (
    LINK_UP_AFTER_S,
    START_BOUND_S,
    StallWatch,
    Wait,
    controller_judge,
    drone_conditions,
    drone_judge,
    one_line,
    station_links,
)


def test_a_condition_is_a_stall_once_it_has_held_long_enough() -> None:
    watch = StallWatch(threshold_s=3.0, log_every_s=5.0)
    assert watch.update(0.0, {"gap": "log message 4 missing"}) == []
    assert watch.update(2.9, {"gap": "log message 4 missing"}) == []
    [wait] = watch.update(3.0, {"gap": "log message 4 missing"})
    assert wait == Wait("gap", "log message 4 missing", 3.0, needs_person=True)
    assert str(wait) == "log message 4 missing for 3 s"
    # It ends when the condition does, and starts again from zero.
    assert watch.update(4.0, {}) == []
    assert watch.update(5.0, {"gap": "log message 4 missing"}) == []


def test_stalls_are_logged_when_they_begin_and_every_few_seconds() -> None:
    watch = StallWatch(threshold_s=1.0, log_every_s=5.0)
    watch.update(0.0, {"ring": "ring stream down"})
    stalls = watch.update(1.0, {"ring": "ring stream down"})
    assert watch.due_for_log(1.0, stalls)
    assert not watch.due_for_log(3.0, watch.update(3.0, {"ring": "ring stream down"}))
    assert watch.due_for_log(6.0, watch.update(6.0, {"ring": "ring stream down"}))
    assert not watch.due_for_log(7.0, watch.update(7.0, {}))


def test_an_expected_wait_is_shown_but_never_logged_nor_in_the_one_line() -> None:
    watch = StallWatch(threshold_s=1.0)
    judge = controller_judge(on_map=True, master=False, catch_up_bound_s=10.0)
    watch.update(0.0, {"standby": "no standby stream"}, judge)
    waits = watch.update(2.0, {"standby": "no standby stream"}, judge)
    assert waits == [Wait("standby", "no standby stream", 2.0, needs_person=False)]
    assert not watch.due_for_log(2.0, waits)
    assert one_line(waits) == ""
    # A stall beside it is logged, and it alone is in the one line.
    holding = {"standby": "no standby stream", "ring": "ring stream down"}
    watch.update(2.0, holding, judge)
    waits = watch.update(3.0, holding, judge)
    assert watch.due_for_log(3.0, waits)
    assert one_line(waits) == "ring stream down for 1 s"


def test_a_controller_expects_no_link_to_the_drone_only_as_a_station_that_is_not_master() -> None:
    station = controller_judge(on_map=True, master=False, catch_up_bound_s=10.0)
    # Neither its standby stream nor the Connect that asks whether it is master.
    assert not station("standby", 60.0) and not station("drone", 60.0)
    # A master must reach the drone; without a map every controller must.
    for link in ("standby", "drone"):
        assert controller_judge(on_map=True, master=True, catch_up_bound_s=10.0)(link, 3.0)
        assert controller_judge(on_map=False, master=False, catch_up_bound_s=10.0)(link, 3.0)
    for stall in ("gap", "ring", "retry", "request 7"):
        assert station(stall, 3.0), stall


def test_catching_up_is_expected_within_the_prepare_timeout() -> None:
    judge = controller_judge(on_map=False, master=True, catch_up_bound_s=10.0)
    assert not judge("catch-up", 10.0)
    assert judge("catch-up", 10.5)


def test_the_drone_waits_for_the_links_of_stations_in_range_or_of_all_without_a_map() -> None:
    ring = [0, 1, 2, 3]
    # With a map: 1 and 2 are in range, 2 holds its stream; 0 and 3 are out of range.
    assert station_links(ring, reachable={2}, in_range={1, 2}) == {
        "link 1": "controller 1 holds no standby stream though the vehicle is in its range"
    }
    # Without one: every controller without a stream.
    assert list(station_links(ring, reachable={0, 2}, in_range=None)) == ["link 1", "link 3"]


def test_a_link_in_range_has_its_time_to_come_up_then_needs_a_person() -> None:
    judge = drone_judge(link_up_bound_s=2.0)  # below the floor: the floor holds
    assert not judge("link 1", LINK_UP_AFTER_S - 0.5)
    assert judge("link 1", LINK_UP_AFTER_S)
    assert not drone_judge(link_up_bound_s=20.0)("link 1", 19.0)
    assert judge("master", 3.0)


def test_the_drone_waits_for_its_controllers_to_start_then_for_its_master() -> None:
    ring, nobody = [0, 1], set[int]()
    waits = drone_conditions(0, False, ring, nobody, None, reached=False)
    assert list(waits) == ["start"]
    judge = drone_judge(link_up_bound_s=0.0)
    assert not judge("start", START_BOUND_S - 1) and judge("start", START_BOUND_S)
    # Once one has reached it, a master without its stream is a stall.
    waits = drone_conditions(0, False, ring, {1}, None, reached=True)
    assert waits == {
        "link 0": "controller 0 holds no standby stream",
        "master": "the master, controller 0, holds no Connect stream",
    }
    assert drone_conditions(0, True, ring, {0, 1}, None, reached=True) == {}
