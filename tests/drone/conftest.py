"""Fixtures: a drone service over the fake vehicle, served in-process on a real port."""

from __future__ import annotations

import sys
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

# The suite runs with --import-mode=importlib, which does not put test folders
# on sys.path; the drone tests share their helpers from this folder.
sys.path.insert(0, str(Path(__file__).parent))

from drone_harness import DroneUnderTest, start_drone


@pytest.fixture
async def drone() -> AsyncIterator[DroneUnderTest]:
    under_test, server = await start_drone()
    yield under_test
    await server.stop(0)
