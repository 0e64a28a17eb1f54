"""``--sim-seeds N``: how many seeds the simulation tests run (``pytest tests/sim --sim-seeds N``).

pytest reads this option only when tests/sim is named on the command line.
"""

from __future__ import annotations

import pytest


def pytest_addoption(parser: pytest.Parser) -> None:
    """Registers ``--sim-seeds`` (only when tests/sim is named on the command line)."""
    parser.addoption(
        "--sim-seeds",
        type=int,
        default=None,
        help="seeds for the simulation's seed tests (default: 3,000 in CI, 100,000 with -m slow)",
    )


@pytest.fixture
def sim_seeds(request: pytest.FixtureRequest) -> int | None:
    """The ``--sim-seeds`` value, None when not given."""
    value = request.config.getoption("--sim-seeds", default=None)
    return int(value) if value is not None else None
