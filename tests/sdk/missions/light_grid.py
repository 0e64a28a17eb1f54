"""The async grid mission, refusing to fly where the heavy dependencies are importable:
proof that it runs in a virtualenv with only baton-sdk (tests/sdk/test_sdk_distribution.py)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import baton.sdk
from baton.missions import grid_async
from baton.sdk.aio import Drone

HEAVY = ("mavsdk", "pymavlink", "matplotlib", "numpy", "pydantic", "yaml", "cryptography")


async def mission(
    drone: Drone, grid: int = 2, spacing_m: float = 20.0, altitude_m: float = 5.0
) -> None:
    """Flies ``grid_async`` after checking what this interpreter can import."""
    found = [name for name in HEAVY if importlib.util.find_spec(name) is not None]
    if found:
        raise RuntimeError(f"{sys.executable} can import {found}: not the SDK's own virtualenv")
    if not Path(baton.sdk.__file__).is_relative_to(sys.prefix):
        raise RuntimeError(f"baton.sdk imported from {baton.sdk.__file__}, not {sys.prefix}")
    print(f"flying from {sys.prefix}", flush=True)
    await grid_async.mission(drone, grid=grid, spacing_m=spacing_m, altitude_m=altitude_m)
