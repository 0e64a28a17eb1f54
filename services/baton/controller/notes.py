"""What a controller says of its effects, and what it keeps of its handovers: one text
for each, so the runtime's log and the simulation's trace read the same.

``note_of`` gives the ``Note`` an effect is reported with (None: it says nothing
itself); the runtime logs it, the simulation traces it. ``Handovers`` keeps the
roles this controller took in handovers, for GetStatus and the benchmarks.
"""

from __future__ import annotations

from dataclasses import dataclass

from baton.controller.core import CoreEffect, FirstNewCall, Note, Record, ReplayAgain
from baton.controller.protocol import Diverged, Fenced, SendLog, TookOver, Unqueued
from baton.v1 import ring_pb2


def note_of(effect: CoreEffect, epoch: int) -> Note | None:
    """The line ``effect`` is reported with (a ``Note`` is its own); ``epoch``: the
    controller's now."""
    if isinstance(effect, Note):
        return effect
    if isinstance(effect, SendLog):
        message = effect.message
        return Note(
            "debug",
            "log message sent",
            {
                "dest": effect.dest,
                "mlognr": message.lognr,
                "entries": len(message.entries),
                "handover": message.handover,
            },
        )
    if isinstance(effect, Diverged):
        return Note(
            "warning",
            "the ring's log differs from ours: a takeover framed the same replies in "
            "messages of its own; rejoining as a replica",
            {
                "mlognr": effect.lognr,
                "our_epoch": effect.ours_epoch,
                "ring_epoch": effect.ring_epoch,
            },
        )
    if isinstance(effect, Fenced):
        return Note(
            "warning",
            "log message from a fenced master dropped",
            {
                "mlognr": effect.lognr,
                "origin": effect.origin,
                "message_epoch": effect.epoch,
                "epoch": epoch,
            },
        )
    if isinstance(effect, Unqueued):
        return Note(
            "warning",
            "queued log message of a replaced framing dropped",
            {"mlognr": effect.lognr, "origin": effect.origin, "message_epoch": effect.epoch},
        )
    if isinstance(effect, TookOver):
        return Note("info", "taking over as master", {"old_master": effect.old_master})
    if isinstance(effect, FirstNewCall):
        return Note(
            "info",
            "first new call after the takeover",
            {"reqnr": effect.reqnr, "method": effect.method, "epoch": effect.epoch},
        )
    return None


def replay_again(cid: int, again: ReplayAgain, restarts: int) -> tuple[Note, str]:
    """What a program that gave up on a call the master's program did not is told
    (``ReplayAgain``): the warning, and its call's ABORTED message. A replica's program
    gives up on its own clock while it waits for the log; the master's program may have
    had its reply. The program has run on an answer the mission never had but has acted
    on nothing: it is restarted and replays the log from the start, as Temporal retries
    a workflow task from its history."""
    entry, method, code = again.entry, again.method, again.code
    master_saw = "a reply" if entry.status_code == 0 else f"status {entry.status_code}"
    note = Note(
        "warning",
        "the mission program gave up on a call the master's program did not; it starts "
        "again and replays the log (a deadline on a drone call makes a mission "
        "non-deterministic: wait for the log instead)",
        {
            "reqnr": entry.reqnr,
            "method": method,
            "gave_up": code.name,
            "master_saw": master_saw,
            "restarts": restarts,
        },
    )
    aborted = (
        f"controller {cid}: the program gave up on request {entry.reqnr} ({method}, "
        f"{code.name}) but the master's program got {master_saw}: the program starts "
        "again and replays the log"
    )
    return note, aborted


@dataclass
class HandoverEvent:
    """A handover as this controller saw it, for the status and the report."""

    role: ring_pb2.HandoverRole.ValueType  # ControllerHandover.role
    peer: int
    lognr: int
    reqnr: int
    log_bytes: int
    at: float
    epoch: int = 0
    drone_after_reqnr: int = 0
    holds_reqnr: int = 0  # a taker's
    first_new_reqnr: int = 0  # a taker's first call beyond the retained replies
    first_new_at: float = 0.0


class Handovers(list[HandoverEvent]):
    """The handovers this controller took part in, in order."""

    def take(self, effect: CoreEffect, at: float) -> None:
        """Keeps what a bookkeeping effect says (``at``: Unix seconds now)."""
        if isinstance(effect, Record):
            self.append(
                HandoverEvent(
                    effect.role,
                    effect.other,
                    effect.lognr,
                    effect.reqnr,
                    effect.log_bytes,
                    at,
                    epoch=effect.epoch,
                    drone_after_reqnr=effect.drone_after_reqnr,
                    holds_reqnr=effect.holds_reqnr,
                )
            )
        elif isinstance(effect, TookOver):
            self.append(
                HandoverEvent(
                    ring_pb2.HANDOVER_ROLE_NEW,
                    effect.old_master,
                    effect.lognr,
                    effect.reqnr,
                    effect.message_bytes,
                    at,
                )
            )
        elif isinstance(effect, FirstNewCall):
            takers = [h for h in self if h.role == ring_pb2.HANDOVER_ROLE_TAKER]
            if takers:
                takers[-1].first_new_reqnr, takers[-1].first_new_at = effect.reqnr, at
