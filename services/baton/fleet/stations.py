"""Stations from a testbed file: its controllers, placed by their ``location`` and
``range_m`` (examples/corridor.yaml's four); and the configuration a mission over
some of them flies with."""

from __future__ import annotations

from collections.abc import Sequence

from baton.config import BatonConfig, ConfigError
from baton.drone.policy import Station
from baton.sdk.types import Position


def stations_of(config: BatonConfig, source: str) -> list[Station]:
    """The controllers of ``config`` (read from ``source``) as stations; ConfigError
    naming the controller without a location or a range, and the fix."""
    stations = []
    for k, c in enumerate(config.controllers):
        if c.location is None or c.range_m is None:
            missing = "location" if c.location is None else "range_m"
            raise ConfigError(
                f"{source}: controllers[{k}].{missing}: controller {c.id} is a station only "
                "with its location and range_m; add them"
            )
        where = Position(c.location.latitude_deg, c.location.longitude_deg)
        stations.append(Station(c.id, where, c.range_m))
    return stations


def ring_config(config: BatonConfig, ring: Sequence[int], first_master: int) -> BatonConfig:
    """``config`` flown by ``ring`` (admission's, in route order) from ``first_master``:
    only the ring's controllers, the ring's order, the first master initial."""
    document = config.model_dump(exclude_unset=True)
    kept = set(ring)
    document["controllers"] = [c for c in document["controllers"] if c["id"] in kept]
    document["ring"] = {**document.get("ring", {}), "order": list(ring)}
    document["initial_master"] = first_master
    return BatonConfig.model_validate(document)
