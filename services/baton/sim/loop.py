"""Virtual time: one event heap, the simulation's only scheduler.

Every event is a plain callback with its arguments, ordered by (time, the
order it was scheduled in), so two runs of one seed take every event in the
same order. Nothing here reads a wall clock or sleeps; time moves only when
the next event is taken.

Simplification: there are no cancellable handles. An event that may have
become moot (a delivery over a stream that broke meanwhile, a timer of a
controller that was killed) carries what it was scheduled for, and its
handler checks that this still holds.
"""

from __future__ import annotations

import heapq
from collections.abc import Callable
from typing import Any

Event = tuple[float, int, Callable[..., None], tuple[Any, ...]]


class Loop:
    """Virtual time in seconds and the events due at it."""

    def __init__(self) -> None:
        self.now = 0.0
        self.events = 0
        self._heap: list[Event] = []
        self._order = 0
        # Called after every event (the World's invariant checker), if set.
        self.after_event: Callable[[], None] | None = None

    def at(self, when: float, callback: Callable[..., None], *args: Any) -> None:
        """Runs ``callback(*args)`` at virtual time ``when`` (never before now)."""
        self._order += 1
        heapq.heappush(self._heap, (max(when, self.now), self._order, callback, args))

    def after(self, delay: float, callback: Callable[..., None], *args: Any) -> None:
        """Runs ``callback(*args)`` ``delay`` virtual seconds from now."""
        self.at(self.now + delay, callback, *args)

    def run(self, until: float, limit: int) -> bool:
        """Takes events up to virtual time ``until`` or ``limit`` events; False if none are left."""
        heap, hook = self._heap, self.after_event
        while heap and heap[0][0] <= until and self.events < limit:
            when, _, callback, args = heapq.heappop(heap)
            self.now = when
            self.events += 1
            callback(*args)
            if hook is not None:
                hook()
        return bool(heap)

    # -- a chosen order (explore.py): any pending event may be taken next -------------

    def pending(self) -> list[Event]:
        """The events scheduled and not taken yet, in the order ``run`` takes them."""
        return sorted(self._heap, key=lambda e: (e[0], e[1]))

    def take(self, event: Event) -> None:
        """Takes ``event`` (one of ``pending``) now: at its time, or now if that has passed."""
        self._heap.remove(event)
        heapq.heapify(self._heap)
        when, _, callback, args = event
        self.now = max(self.now, when)
        self.events += 1
        callback(*args)
        if self.after_event is not None:
            self.after_event()

    @property
    def scheduled(self) -> int:
        """How many events were scheduled so far (the last one's order)."""
        return self._order

    def push(self, event: Event) -> None:
        """Schedules ``event`` again as it was (a duplicated delivery), after those of its time."""
        self._order += 1
        heapq.heappush(self._heap, (event[0], self._order, event[2], event[3]))

    @property
    def next_time(self) -> float | None:
        """When the next event is due, None when nothing is scheduled."""
        return self._heap[0][0] if self._heap else None
