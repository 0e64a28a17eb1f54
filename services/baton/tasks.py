"""Tasks an owner starts and does not await, held until they end.

The event loop keeps only weak references to its tasks: a task that nobody
holds can be garbage-collected before it finishes (``asyncio.create_task``'s
documentation says to keep a reference). An owner that starts work in the
background (the controller node's session events and rejoins, the drone
service's invocations) spawns it on its own ``TaskSet`` instead of calling
``create_task`` and dropping the result.
"""

from __future__ import annotations

import asyncio
from collections.abc import Coroutine
from typing import Any, TypeVar

T = TypeVar("T")


class TaskSet:
    """The background tasks of one owner, each held from its start to its end."""

    def __init__(self) -> None:
        self._tasks: set[asyncio.Task[Any]] = set()

    def spawn(self, work: Coroutine[Any, Any, T], name: str | None = None) -> asyncio.Task[T]:
        """Starts ``work`` as a task on the running loop and holds it until it is done."""
        task = asyncio.get_running_loop().create_task(work, name=name)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    def __len__(self) -> int:
        """How many are still running."""
        return len(self._tasks)

    async def drain(self) -> None:
        """Waits until every task held has ended, those started meanwhile too."""
        while self._tasks:
            await asyncio.wait(set(self._tasks))

    def cancel(self) -> None:
        """Cancels every task still running."""
        for task in self._tasks:
            task.cancel()
