"""The drone's own invariants, as pure checks: what the drone alone can see of the
protocol's promises (docs/simulation.md, "Invariants").

- The drone accepts requests of one controller per epoch: two masters in one
  epoch would both be executed.
- Its epoch, last request number and watermark never move back, and the
  watermark never passes the last request: a number given out twice, or a
  reply let go that a controller still lacks, breaks exactly once.

The simulation checks these after every event (``baton.sim.invariants``), and a
running drone checks them at every request it admits when
``BATON_CHECK_INVARIANTS=1`` (the end-to-end tests turn it on): a broken one is
``InvariantBroken``, which stops the drone service loudly rather than let it fly
on in a state the protocol says cannot be.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

CHECK_ENV = "BATON_CHECK_INVARIANTS"
# The exit code of a process stopped by a broken invariant.
INVARIANT_EXIT = 70


def checking() -> bool:
    """Whether this process checks the invariants as it runs (``BATON_CHECK_INVARIANTS=1``)."""
    return os.environ.get(CHECK_ENV) == "1"


class InvariantBroken(AssertionError):
    """A state the protocol says cannot be: a defect of baton, not of its input."""


@dataclass
class DroneWatch:
    """What the checks remember: the last values seen, and each epoch's controller."""

    epoch: int = 0
    last_reqnr: int = 0
    watermark: int = 0
    owners: dict[int, int] = field(default_factory=dict)

    def accepted(self, epoch: int, cid: int, reqnr: int) -> str | None:
        """Request ``reqnr`` of controller ``cid`` in ``epoch`` accepted: what is wrong
        (another controller's requests were accepted in that epoch), or None."""
        owner = self.owners.setdefault(epoch, cid)
        if owner != cid:
            return (
                f"epoch {epoch}: requests of controller {owner} and of controller {cid} "
                f"(reqnr {reqnr}) accepted"
            )
        return None

    def moved(self, epoch: int, last_reqnr: int, watermark: int) -> str | None:
        """The drone's epoch, last reqnr and watermark now: what moved back, or a
        watermark past the last request; None if nothing is wrong."""
        now = (epoch, last_reqnr, watermark)
        was = (self.epoch, self.last_reqnr, self.watermark)
        self.epoch, self.last_reqnr, self.watermark = now
        for name, old, new in zip(("epoch", "last reqnr", "watermark"), was, now, strict=True):
            if new < old:
                return f"the drone's {name} went back from {old} to {new}"
        if watermark > last_reqnr:
            return f"the drone's watermark {watermark} is past its last reqnr {last_reqnr}"
        return None
