"""What the drone's watches are given of the controllers, as one value.

The master watch (``DroneCore.takeover_due``, ``master_watch``) and the failsafe
watch (``DroneCore.failsafe_check``) judge from the same sight: which controllers
hold a stream to the drone now (a standby or a Connect stream), whether the master
holds its Connect stream (a master that serves is not lost), and which controllers'
radio range holds the vehicle (None: no handover policy, every controller counts).
Each driver (``DroneService``, the simulation's ``SimDrone``) reads its streams into
a ``DroneSight``; the core's calls are assembled here, once.
"""

from __future__ import annotations

from dataclasses import dataclass

from baton.drone.core import DroneCore
from baton.drone.effects import DroneEffect
from baton.drone.safety import Failsafe, ModeSeen
from baton.drone.sequencer import TakeoverDue
from baton.v1 import drone_api_pb2 as api


@dataclass(frozen=True)
class DroneSight:
    """The controllers as the drone sees them now."""

    holders: set[int]  # every controller holding a standby or a Connect stream
    master_connected: bool  # the master holds its Connect stream
    in_range: set[int] | None = None  # whose radio range holds the vehicle; None: all

    def connected(self, core: DroneCore) -> set[int]:
        """The controllers that hold the master's Connect stream: the master, or nobody."""
        return {core.seq.master} if self.master_connected else set()

    def takeover_due(self, core: DroneCore, now: float) -> TakeoverDue | None:
        """Whether the master is lost now, and who takes over (``DroneCore.takeover_due``)."""
        return core.takeover_due(now, self.holders, self.connected(core), self.in_range)

    def master_watch(
        self, core: DroneCore, now: float, position: api.Position | None = None
    ) -> list[DroneEffect]:
        """A tick of the master watch under the execution lock (``DroneCore.master_watch``)."""
        return core.master_watch(now, self.holders, self.connected(core), self.in_range, position)

    def failsafe_check(
        self,
        core: DroneCore,
        now: float,
        airborne: bool,
        battery_percent: float,
        position: api.Position | None,
        seen: ModeSeen,
        nearest: int | None = None,
    ) -> Failsafe | None:
        """The failsafe due now for the vehicle as it is seen (``DroneCore.failsafe_check``)."""
        return core.failsafe_check(
            now, airborne, battery_percent, position, seen, self.holders, self.in_range, nearest
        )
