"""The live view's reading of the network: the registry's stations and missions, each
station's ``GetStation`` and each mission in flight's drone's ``GetStatus``, asked at
once with ``operations``' deadline, made into the page's document by
``state.fleet_view``.

The registry is opened afresh on every read, so a mission admitted or cancelled,
or a station drained, shows on the next; nothing is written to it.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from baton.config import BatonConfig
from baton.fleet.operations import ask_drone, ask_stations, at_once
from baton.fleet.registry import IN_FLIGHT, Registry
from baton.rpc.tls import Tls
from baton.view.state import fleet_view


def read_network(registry_path: Path, network: BatonConfig, tls: Tls | None) -> dict[str, Any]:
    """The view's document now (blocking: a few seconds at most, ``ASK_TIMEOUT_S``)."""
    with Registry(registry_path) as registry:
        stations = registry.stations()
        missions = registry.missions()
    flying = [m for m in missions if m.state == IN_FLIGHT]
    station_replies = ask_stations(network, [s.station.id for s in stations], tls)
    drones = at_once(lambda m: ask_drone(m, tls), flying)
    drone_replies = {m.id: reply for m, reply in drones.items()}
    return fleet_view(stations, missions, station_replies, drone_replies, time.time())
