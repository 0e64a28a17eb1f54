"""The deadlines a controller's core armed, held by a driver over its own scheduler.

The core says when a decision falls due (``Arm``, ``Disarm`` in
``ControllerCore.ready``); a driver keeps one pending deadline per timer and
hands the core the firing (``ControllerCore.timer_fired``). The runtime
schedules on asyncio's ``loop.call_at``, the simulation on its virtual
``Loop.at``: the same table over either, so both fire exactly what the core
armed and nothing else.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from baton.controller.core import Arm, Disarm, Timer

# ``schedule(at, callback, *args)``: runs ``callback(*args)`` at ``at``; what it returns
# is cancelled (``cancel()``) when the deadline is replaced, if it can be.
Schedule = Callable[..., Any]


class TimerTable:
    """One pending deadline per timer: arming again replaces it, a replaced or disarmed
    one never fires (a scheduler without cancellable handles still runs it, and it is
    dropped here)."""

    def __init__(self, schedule: Schedule, fire: Callable[[Timer], None]) -> None:
        self._schedule = schedule
        self._fire = fire
        # The pending deadline of each timer: the arming it came from, and its handle.
        self._pending: dict[Timer, tuple[int, Any]] = {}
        self._armings = 0
        self._closed = False

    def apply(self, effect: Arm | Disarm) -> None:
        """Carries out the core's ``Arm`` or ``Disarm``."""
        self._drop(effect.timer)
        if isinstance(effect, Arm) and not self._closed:
            self._armings += 1
            handle = self._schedule(effect.at, self._due, effect.timer, self._armings)
            self._pending[effect.timer] = (self._armings, handle)

    def clear(self) -> None:
        """No deadline pending (the core they were armed for is replaced)."""
        for timer in list(self._pending):
            self._drop(timer)

    def close(self) -> None:
        """No deadline pending, and none armed from now on (the driver stops)."""
        self._closed = True
        self.clear()

    def _drop(self, timer: Timer) -> None:
        pending = self._pending.pop(timer, None)
        cancel = getattr(pending[1], "cancel", None) if pending is not None else None
        if cancel is not None:
            cancel()

    def _due(self, timer: Timer, arming: int) -> None:
        pending = self._pending.get(timer)
        if pending is None or pending[0] != arming:
            return
        del self._pending[timer]
        self._fire(timer)

    @property
    def pending(self) -> set[Timer]:
        """The timers with a deadline pending."""
        return set(self._pending)
