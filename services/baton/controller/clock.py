"""The mission clock: Clock.Sleep and Clock.Now on the simulation's time scale.

With the sim vehicle sped up X times, mission time runs X times faster too, so
that "poll every second" stays one simulated second and the paper's mission
keeps its shape (docs/design.md, "One time scale"). Mission time is counted from
midnight UTC of the current day, the same origin on every controller, so the
time stays plausible and replicas on different nodes agree up to their clocks.
"""

from __future__ import annotations

import asyncio
import math
import time

_DAY_S = 86_400


class MissionClock:
    """Scaled wall-clock time for one controller."""

    def __init__(self, speedup: float = 1.0) -> None:
        if not math.isfinite(speedup) or speedup <= 0:
            raise ValueError(f"speedup must be a finite number > 0, got {speedup}")
        self.speedup = speedup
        self._origin = math.floor(time.time() / _DAY_S) * _DAY_S

    def now(self) -> float:
        """Mission time, Unix seconds."""
        return self._origin + (time.time() - self._origin) * self.speedup

    async def sleep(self, mission_seconds: float) -> None:
        """Sleeps for ``mission_seconds`` of mission time."""
        await asyncio.sleep(mission_seconds / self.speedup)
