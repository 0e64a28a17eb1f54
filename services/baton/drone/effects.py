"""What the drone's core (``DroneCore``) asks its driver to do after an event.

Every event of the core that moves the master or books a request returns a
list of these effects. The driver (``drone/service.py``, the simulation's
``sim/drone.py``) applies them in the order given, under its execution lock,
before it takes the next event; the core puts them in this order:

1. ``Book`` / ``Abandon`` / ``SaveCounters``: what to persist. A driver with a store writes
   it before anything below reaches a controller, so a restart never
   forgets a switch or an outcome that a controller heard of.
2. ``Switched`` / ``Preparing``: what changed for the Connect streams. The
   driver wakes the stream that must carry the news (the old master's, for
   its handover notice; the master's, for a PrepareHandover); the stream
   then asks the core what to send (``connects.ConnectStream``).
3. ``TellTakeOver``: the TakeOver for the taker's newest standby stream.
4. ``Note``: what to report in the log (or the simulation's trace).

Effects are data: no asyncio, no gRPC, no clock.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from baton.drone.sequencer import Served
from baton.v1 import drone_pb2


@dataclass(frozen=True)
class Book:
    """A request's outcome booked (``Sequencer.served``): the counters, its reply and its
    audit entry, persisted in one transaction (``DroneStore.served``)."""

    served: Served


@dataclass(frozen=True)
class Abandon:
    """The request being executed reached nothing (or is a read a restart cut off): its
    intent is dropped, its number stays unused, the same request may come again."""


@dataclass(frozen=True)
class SaveCounters:
    """The counters (master, epoch's handovers, watermark) changed: persist them."""


@dataclass(frozen=True)
class Switched:
    """The master moved (``record``). The driver wakes the old master's Connect stream,
    which owes it the handover notice, and a Handover call waiting for the switch; a
    master chosen by the script or an operator pins the handover policy."""

    record: drone_pb2.HandoverRecord


@dataclass(frozen=True)
class Preparing:
    """A prepared handover began: the master's Connect stream carries ``notice`` next."""

    notice: drone_pb2.PrepareHandover


@dataclass(frozen=True)
class TellTakeOver:
    """Tell the taker of ``record`` on its newest standby stream (the retained replies
    it lacks follow its Connected); ``lost_at``: when the lost master was last seen
    (0: a takeover asked for, not a loss)."""

    record: drone_pb2.HandoverRecord
    take_over: drone_pb2.TakeOver
    lost_at: float = 0.0


@dataclass(frozen=True)
class Note:
    """A line for the log: ``level`` is ``info`` or ``warning``."""

    level: str
    event: str
    fields: Mapping[str, Any] = field(default_factory=dict)


def pins_policy(record: drone_pb2.HandoverRecord) -> bool:
    """Whether the switch of ``record`` pins the handover policy to its new master: a
    master the script or an operator chose overrides the policy."""
    return record.trigger in (drone_pb2.HANDOVER_TRIGGER_SCRIPT, drone_pb2.HANDOVER_TRIGGER_RPC)


DroneEffect = Book | Abandon | SaveCounters | Switched | Preparing | TellTakeOver | Note


def take_over_event(record: drone_pb2.HandoverRecord, watermark: int) -> drone_pb2.TakeOver:
    """The TakeOver that tells the taker of ``record`` (small: the replies it lacks
    follow its Connected)."""
    return drone_pb2.TakeOver(
        old_master=record.old_master,
        epoch=record.epoch,
        after_reqnr=record.after_reqnr,
        watermark_reqnr=watermark,
    )
