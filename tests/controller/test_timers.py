"""The drivers' table of the core's deadlines (``controller/timers.py``)."""

from __future__ import annotations

from typing import Any

from baton.controller.core import Arm, Disarm, Timer
from baton.controller.timers import TimerTable
from baton.sim.loop import Loop


def test_a_timer_armed_again_or_disarmed_fires_only_its_last_deadline() -> None:
    """Over a scheduler without cancellable handles (the simulation's loop), a replaced
    deadline still runs and is dropped; only the one armed last fires, once."""
    loop, fired = Loop(), []
    table = TimerTable(loop.at, lambda timer: fired.append((timer, loop.now)))
    table.apply(Arm(Timer.GAP, 5.0))
    table.apply(Arm(Timer.GAP, 3.0))  # replaces the one at 5
    table.apply(Arm(Timer.ROUTE, 1.0))
    table.apply(Arm(Timer.PREPARATION, 2.0))
    table.apply(Disarm(Timer.PREPARATION))
    loop.run(until=10.0, limit=100)
    assert fired == [(Timer.ROUTE, 1.0), (Timer.GAP, 3.0)] and table.pending == set()


def test_a_replaced_deadline_is_cancelled_where_the_scheduler_can() -> None:
    handles: list[Any] = []

    class Handle:
        cancelled = False

        def cancel(self) -> None:
            self.cancelled = True

    def schedule(at: float, callback: Any, *args: Any) -> Handle:
        handles.append(Handle())
        return handles[-1]

    table = TimerTable(schedule, lambda timer: None)
    table.apply(Arm(Timer.GAP, 1.0))
    table.apply(Arm(Timer.GAP, 2.0))
    table.clear()
    assert [h.cancelled for h in handles] == [True, True] and table.pending == set()
    table.apply(Arm(Timer.ROUTE, 3.0))
    table.close()  # the driver stops: nothing armed from now on
    table.apply(Arm(Timer.ROUTE, 4.0))
    assert len(handles) == 3 and handles[2].cancelled and table.pending == set()
