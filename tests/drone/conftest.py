"""Fixtures: a drone service over the fake vehicle, served in-process on a real port."""

from __future__ import annotations

from collections.abc import AsyncIterator

import pytest
from drone_harness import DroneUnderTest, start_drone


@pytest.fixture
async def drone() -> AsyncIterator[DroneUnderTest]:
    under_test, server = await start_drone()
    yield under_test
    await server.stop(0)
