"""baton-sdk as a mission author gets it: ``pip install ./clients`` into a fresh virtualenv
(no --system-site-packages) installs the SDK, grpcio and protobuf only, and a mission run
from that virtualenv flies a real local testbed, with handovers.

Building the virtualenv takes about 8 s here with pip's cache warm (python -m venv, then
pip builds the wheel with hatchling and installs grpcio and protobuf from the cache).
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
MISSIONS = Path(__file__).parent / "missions"
# What the SDK must not pull in (the services' dependencies).
HEAVY = {"mavsdk", "pymavlink", "matplotlib", "numpy", "pydantic", "pyyaml", "cryptography"}


@pytest.fixture(scope="module")
def sdk_python(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The python of a fresh virtualenv with ``pip install ./clients`` done."""
    venv = tmp_path_factory.mktemp("sdk") / "venv"
    started = time.monotonic()
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    python = venv / "bin" / "python"
    install = subprocess.run(
        [
            str(python),
            "-E",  # what the virtualenv holds, whatever PYTHONPATH says
            "-m",
            "pip",
            "install",
            "--quiet",
            "--disable-pip-version-check",
            str(REPO / "clients"),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert install.returncode == 0, install.stdout + install.stderr
    print(f"virtualenv with baton-sdk in {time.monotonic() - started:.1f} s")
    yield python


def test_pip_install_clients_brings_grpcio_and_protobuf_only(sdk_python: Path) -> None:
    pip = [str(sdk_python), "-E", "-m", "pip", "--disable-pip-version-check"]
    listing = subprocess.run(
        [*pip, "list", "--format=json"],
        capture_output=True,
        text=True,
        check=True,
    )
    installed = {p["name"].lower().replace("_", "-") for p in json.loads(listing.stdout)}
    assert {"baton-sdk", "grpcio", "protobuf"} <= installed
    assert not installed & HEAVY, installed
    # Everything the distribution ships imports there, py.typed included; the services do not.
    check = """
import importlib, importlib.resources, pkgutil
import baton.sdk, baton.missions
for package in (baton.sdk, baton.missions):
    for module in pkgutil.iter_modules(package.__path__):
        importlib.import_module(f"{package.__name__}.{module.name}")
for package in ("baton.sdk", "baton.missions", "baton.v1"):
    assert importlib.resources.files(package).joinpath("py.typed").is_file(), package
try:
    import baton.controller
except ModuleNotFoundError:
    print("no services")
"""
    result = subprocess.run([str(sdk_python), "-E", "-c", check], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "no services"


def fly_light_grid(python: Path, *args: str, timeout: float) -> subprocess.CompletedProcess[str]:
    """``baton testbed`` flying tests/sdk/missions/light_grid.py from ``python``."""
    mission = ["--mission", str(MISSIONS / "light_grid.py"), "--mission-python", str(python)]
    return subprocess.run(
        [sys.executable, "-m", "baton.cli", "testbed", *mission, *args],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_a_mission_from_the_sdk_virtualenv_flies_the_testbed(
    sdk_python: Path, tmp_path: Path
) -> None:
    report_path = tmp_path / "report.json"
    result = fly_light_grid(
        sdk_python,
        *("--speedup", "20", "--no-links", "--handover", "8:1", "--handover", "16:2"),
        *("--report", str(report_path), "--workdir", str(tmp_path / "w")),
        timeout=300,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "mission COMPLETED" in result.stdout
    report = json.loads(report_path.read_text())
    assert report["exactly_once"] and report["replicas_consistent"]
    assert [h["to"] for h in report["handovers"]] == [1, 2]
    assert report["handovers_missed"] == []
    assert report["mission"]["pictures"] == 4
    # The program ran from the SDK's virtualenv (light_grid.py refuses to fly elsewhere).
    log = (tmp_path / "w" / "logs" / "controller-0.log").read_text()
    assert f"flying from {sdk_python.parent.parent}" in log


def test_a_python_without_the_sdk_is_refused_up_front(tmp_path: Path) -> None:
    bare = tmp_path / "bare"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(bare)], check=True)
    result = fly_light_grid(bare / "bin" / "python", timeout=60)
    assert result.returncode != 0
    assert "cannot import baton.sdk.run" in result.stderr
    assert "pip install ./clients" in result.stderr
