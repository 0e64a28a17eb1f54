"""Fixtures for link tests: the endpoints of ``link_endpoints`` behind a proxy."""

from __future__ import annotations

import sys
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

# The suite runs with --import-mode=importlib, which does not put test folders
# on sys.path; the link tests share their endpoints from this folder.
sys.path.insert(0, str(Path(__file__).parent))

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
