"""The controller protocol at a mission's start, for the tests that feed it events."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace
from typing import Any

from baton.controller.protocol import ControllerProtocol


def started(
    cid: int, ring: list[int], flush_limit: int, initial_master: int = 0
) -> ControllerProtocol:
    """A controller at the mission's start: the predecessor holds nothing yet, and the
    drone grants the initial master epoch 1."""
    p = ControllerProtocol(cid, ring, flush_limit)
    p.start()
    p.on_sync(0)
    if cid == initial_master:
        p.on_granted(1)
    return p


def connected_session() -> Any:
    """A stand-in for a controller's drone session whose Connect stream is up, for the
    tests that call ``ControllerNode``'s event handlers without a drone."""
    session = SimpleNamespace(connected=asyncio.Event())
    session.connected.set()
    return session
