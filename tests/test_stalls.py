"""``StallWatch``: a condition becomes a stall after its threshold, and is logged now and then."""

from __future__ import annotations

from baton.stalls import StallWatch


def test_a_condition_is_a_stall_once_it_has_held_long_enough() -> None:
    watch = StallWatch(threshold_s=3.0, log_every_s=5.0)
    assert watch.update(0.0, {"gap": "log message 4 missing"}) == []
    assert watch.update(2.9, {"gap": "log message 4 missing"}) == []
    assert watch.update(3.0, {"gap": "log message 4 missing"}) == ["log message 4 missing for 3 s"]
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
