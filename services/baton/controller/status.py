"""What a controller believes at its start, and what it says it waits for: pure
functions of its core's state and of what its driver sees (streams up or down).

``recover``: a controller restarted with a log file handles the file's messages
as if received, in log-number order, before anything else: it believes what
its history says (the log, the requests answered, the framings), and the epoch
of the mastership whose log the file holds, told to the drone on Connect so
that the drone fences it if a takeover gave that log up while it was down. The
forwards of those messages are not sent: the successor says what it lacks when
its stream opens, and is given that from the history. A file the protocol
refuses stops the mission (DATA_LOSS): the controller cannot know what it
answered.

``holding``: each condition that would be a stall if it lasted, keyed for the
watchdog (``stalls.StallWatch``), which judges how long each may last; the
runtime's GetStatus ``waiting`` line and the simulation's liveness report are
made of these.
"""

from __future__ import annotations

from dataclasses import dataclass

import grpc

from baton.controller.core import ControllerCore, CoreEffect, Fail, Note
from baton.controller.history import LogHistory
from baton.controller.protocol import ControllerProtocol, ProtocolError


def recover(core: ControllerCore, history: LogHistory, cid: int) -> list[CoreEffect]:
    """The protocol takes the history's messages (the module's rule); the effects say
    what came of it: a Note of what was recovered, or a Fail."""
    protocol = core.protocol
    lognrs = list(history.above(0))
    protocol.epoch = history.mastership_epoch
    for lognr in lognrs:
        try:
            protocol.on_log(history.get(lognr))
        except ProtocolError as exc:
            where = history.path if history.path is not None else "(in memory)"
            return [Fail(f"controller {cid}: log file {where}: {exc}", grpc.StatusCode.DATA_LOSS)]
    if not lognrs:
        return []
    return [
        Note(
            "info",
            "recovered from the log file",
            {"path": str(history.path), "messages": len(lognrs), "up_to_lognr": protocol.lognr},
        )
    ]


@dataclass(frozen=True)
class Sight:
    """What a controller's driver sees of its streams now."""

    # The drone session's address and whether its Connect stream is up (None: no session).
    drone: tuple[str, bool] | None = None
    standby_address: str = ""
    standby_up: bool = True
    # The request the drone has now (reqnr, method) and an operator's pause holding it.
    in_flight: tuple[int, str] | None = None
    operator_pause: str = ""
    # The stream to the successor: up, and how many messages it has not acknowledged
    # (None: no such stream yet).
    successor_link: tuple[bool, int] | None = None


def catch_up_wait(p: ControllerProtocol) -> str:
    """What a master that has not caught up (``ControllerProtocol.caught_up``) waits for,
    the first of its conditions that does not hold."""
    if p.catch_up_to is None:
        return f"controller {p.predecessor} has not said what it holds"
    if p.lognr < p.catch_up_to:
        return f"handled log message {p.lognr} of {p.catch_up_to}"
    if p.held_reqnr < p.must_hold_reqnr:
        # The drone let go of the replies below its watermark when every controller
        # held them; no live one says it holds them now. A controller restarted with
        # its log file gives them to the ring again.
        return (
            f"the drone let go of its replies up to request {p.must_hold_reqnr} (its "
            f"watermark at the takeover), and we hold up to request {p.held_reqnr}; "
            f"our predecessor holds no more (log message {p.catch_up_to}): "
            "waiting for a controller that holds them (one restarted with its log file "
            "gives them again)"
        )
    return (
        f"waiting for the old master's handover message of epoch {p.mastership.owed}, "
        "which carries its log"
    )


def holding(protocol: ControllerProtocol, routed_around: list[int], sight: Sight) -> dict[str, str]:
    """What holds now that would be a stall if it lasted, by watchdog key."""
    p = protocol
    held: dict[str, str] = {}
    missing = p.missing_lognr
    if missing is not None and p.log_queue:
        held["gap"] = (
            f"log message {missing} missing while {len(p.log_queue)} later ones "
            f"are queued (up to {max(p.log_queue)})"
        )
    elif missing is not None:
        held["gap"] = (
            f"our handover message {missing} has not come back round, though we "
            f"handled up to {p.lognr}: our history lacks it"
        )
    if sight.drone is not None and not sight.drone[1]:
        held["drone"] = f"no Connect stream to the drone at {sight.drone[0]}"
    if not sight.standby_up:
        held["standby"] = (
            f"no standby stream to the drone at {sight.standby_address}: the drone "
            "cannot make this controller master if the master is lost"
        )
    if p.master and not p.caught_up:
        held["catch-up"] = (
            f"master by the drone's word (epoch {p.epoch}) but catching up with the ring: "
            + catch_up_wait(p)
        )
    if sight.in_flight is not None:
        reqnr, method = sight.in_flight
        sent = f"request {reqnr} ({method}) sent, no answer yet"
        if sight.operator_pause:
            held["paused"] = f"{sent}: it waits at the drone, {sight.operator_pause}"
        else:
            held[f"request {reqnr}"] = sent
    if sight.successor_link is not None and not sight.successor_link[0]:
        held["ring"] = (
            f"ring stream to controller {p.successor} down "
            f"({sight.successor_link[1]} messages not acknowledged)"
        )
    if routed_around:
        skipped = ", ".join(str(cid) for cid in routed_around)
        held["routed"] = (
            f"ring routed around controller {skipped} (unreachable) to controller {p.successor}"
        )
    return held
