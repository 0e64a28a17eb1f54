"""The testbed's ring from mission admission (``baton testbed --admit``): its
controllers are the stations (their ``location`` and ``range_m``), the mission's
route is flown from ``drone.home``; the ring is the controllers that cover the
route, in route order, the initial master the one nearest take-off, and the
controllers that cover none of it are not started. A route with a stretch no
controller covers is refused before anything starts (``fleet/admission.py``)."""

from __future__ import annotations

from collections.abc import Sequence

from baton.config import BatonConfig
from baton.fleet.admission import Admitted, Refused, admit_mission
from baton.fleet.stations import ring_config, stations_of
from baton.sdk.types import Position

# The testbed flies one drone and keeps no registry: no other mission is in flight.
TESTBED_DRONE = "drone"


def admitted_config(
    config: BatonConfig, route: Sequence[Position], source: str
) -> tuple[BatonConfig, Admitted]:
    """``config`` with the ring and the initial master admission chose for ``route``,
    and only the controllers in that ring; ValueError with the refusal (the uncovered
    stretches named) otherwise."""
    decision = admit_mission(TESTBED_DRONE, route, stations_of(config, source), {})
    if isinstance(decision, Refused):
        raise ValueError(f"--admit: the mission is refused: {decision.message()}")
    return ring_config(config, decision.ring, decision.first_master), decision


def describe(config: BatonConfig, before: BatonConfig, decision: Admitted) -> str:
    """For a person: the admitted ring, where the route enters each range, the first
    master, and the controllers left out."""
    ring = ", ".join(f"{sid} (from {decision.enters_at_m[sid]:.0f} m)" for sid in decision.ring)
    left_out = [c.id for c in before.controllers if c.id not in decision.ring]
    line = (
        f"admission: ring {ring} of a {decision.length_m:.0f} m route; first master "
        f"{config.master_id}, the nearest to take-off"
    )
    if left_out:
        line += f"; controller(s) {', '.join(map(str, left_out))} cover none of it: not started"
    return line
