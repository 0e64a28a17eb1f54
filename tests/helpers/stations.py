"""A mission's configuration over stations started by ``baton.testbed.fleet``."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from baton.config import BatonConfig
from baton.testbed.fleet import StationPart


def mission_config(
    drone_address: str,
    stations: dict[int, StationPart],
    ring: Sequence[int],
    certs: Path,
    speedup: float = 20.0,
) -> BatonConfig:
    """A mission's configuration: its drone, and its ring's stations at their ports."""
    return BatonConfig.model_validate(
        {
            "drone": {"address": drone_address},
            "controllers": [{"id": sid, "address": stations[sid].address} for sid in ring],
            "ring": list(ring),
            "speedup": speedup,
            "flush_limit": 0,
            "tls": {"certs": str(certs)},
        }
    )


def as_text(config: BatonConfig) -> str:
    """The configuration as StartMission carries it (JSON, which YAML reads)."""
    return config.model_dump_json(exclude_unset=True)
