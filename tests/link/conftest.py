"""Fixtures for link tests: the endpoints of ``link_endpoints`` behind a proxy."""

from __future__ import annotations

from collections.abc import AsyncIterator

import pytest
from link_endpoints import Echo, Sink


@pytest.fixture
async def sink() -> AsyncIterator[Sink]:
    server = Sink()
    await server.start()
    yield server
    await server.stop()


@pytest.fixture
async def echo() -> AsyncIterator[Echo]:
    server = Echo()
    await server.start()
    yield server
    await server.stop()
