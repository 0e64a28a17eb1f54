"""Waiting on a condition with a deadline: the one helper the tests share (``eventually``
for async tests, ``until`` for sync ones)."""

from __future__ import annotations

import asyncio
import inspect
import time
from collections.abc import Awaitable, Callable
from typing import Any

# Wall-clock budget for any one step of a test, generous for a loaded 2-core CI box.
STEP_TIMEOUT_S = 20.0


async def eventually(
    check: Callable[[], Awaitable[Any]] | Callable[[], Any],
    what: str,
    timeout_s: float = STEP_TIMEOUT_S,
) -> Any:
    """Polls ``check`` (plain or async) until it returns something truthy; fails after the
    deadline, saying what it waited for and the last value."""
    deadline = time.monotonic() + timeout_s
    last: Any = None
    while time.monotonic() < deadline:
        last = check()
        if inspect.isawaitable(last):
            last = await last
        if last:
            return last
        await asyncio.sleep(0.02)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what} (last: {last!r})")


def until(check: Callable[[], Any], what: str, timeout_s: float = STEP_TIMEOUT_S) -> Any:
    """``eventually`` for a test that cannot run an event loop (one driving playwright's
    sync API): polls ``check`` until it returns something truthy; fails after the
    deadline, saying what it waited for and the last value."""
    deadline = time.monotonic() + timeout_s
    last: Any = None
    while time.monotonic() < deadline:
        last = check()
        if last:
            return last
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what} (last: {last!r})")
