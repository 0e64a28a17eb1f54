"""The oracles: what must hold after a run, judged from the ground truth, not the code's word.

Each oracle reads what the simulation recorded outside the code under
test: the vehicle's and the camera's own counts, what each mission
program was answered, which controllers the drone accepted requests from
in each epoch, and the virtual time at which programs finished.

1. ``at-most-once``: every command and picture acted on at most once
   (counted by the vehicle and camera, by the mission call's unique
   request), every read at most once unless a drone restart cut it off.
2. ``exactly-once``: every drone call a program was answered OK was acted
   on exactly once, and the reply it got is the one the vehicle or camera
   produced for it.
3. ``same-replies``: every incarnation's consumed entries (reqnr, status,
   reply) and every program's answers are a prefix of the longest, and
   entry k is request k.
4. ``one-master-per-epoch``: the drone never accepted requests of two
   controllers in one epoch.
5. ``liveness``: after the fault window, every controller's program
   finished within the quiet bound; ``no-failure``: no controller stopped
   its mission (a refusal judged DISAGREE, a non-determinism error, a
   protocol error), and no program was answered UNAVAILABLE (nothing reached
   the vehicle: the master sends the request again, for longer than any fault).
6. ``bounded``: once finished, every log queue, unacknowledged message,
   abandoned call and the received-numbers set beyond its watermark is
   empty, and the drone's reply cache never outgrew its window.
7. ``lies-refused`` (``--lying``): every frame the lying station forged
   was refused by its receiver's core (lying.py).
8. ``picture-placed``: no picture taken while the vehicle's link was out:
   its place unknown, it cannot be told to be the waypoint's (the drone
   refuses it UNAVAILABLE and the master sends it again).

Besides the oracles, a check of the drone's own word (not ground truth):
``prepared-record``: every handover the drone prepared is recorded as
``prepared`` (the target caught up: within ``PREPARED_BOUND_BYTES``, not
timed out) or as a forced fallback (``cooperative``, ``prepare_timed_out``,
decided at or after the drone's prepare timeout).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import TYPE_CHECKING

import grpc

from baton.drone.sequencer import PREPARED_BOUND_BYTES
from baton.rpc.labels import label
from baton.sim.mission import Kind
from baton.v1 import drone_pb2

UNAVAILABLE = grpc.StatusCode.UNAVAILABLE.value[0]

if TYPE_CHECKING:
    from baton.sim.controller import SimController
    from baton.sim.world import World

ORACLES = (
    "at-most-once",
    "exactly-once",
    "same-replies",
    "one-master-per-epoch",
    "liveness",
    "no-failure",
    "bounded",
    "prepared-record",
    "nothing-in-failsafe",
    "nothing-while-paused",
    "nothing-after-abort",
    "lies-refused",
    "picture-placed",
)


@dataclass(frozen=True)
class Violation:
    """One oracle that failed, and what it saw."""

    oracle: str
    detail: str

    def __str__(self) -> str:
        return f"[{self.oracle}] {self.detail}"


def check(world: World) -> list[Violation]:
    """Every oracle over a finished run."""
    found: list[Violation] = []
    found += _at_most_once(world)
    found += _exactly_once(world)
    found += _same_replies(world)
    found += [Violation("one-master-per-epoch", c) for c in world.drone.stats.epoch_conflicts]
    failures = _failures(world)
    found += failures
    stalled = _liveness(world)
    found += stalled
    if not stalled and not failures:
        found += _bounded(world)
    found += _prepared_records(world)
    found += _nothing_in_failsafe(world)
    found += _nothing_while_paused_or_ended(world)
    found += [
        Violation(
            "picture-placed",
            f"picture of request {picture.reqnr} taken at {picture.time:.3f}s with the "
            "vehicle's link out: its place unknown",
        )
        for picture in world.drone.camera.unplaced
    ]
    found += [
        Violation(
            "lies-refused",
            f"controller {lie.receiver} believed the {lie.kind} frame (log message "
            f"{lie.lognr}) controller {lie.liar} forged at {lie.at:.3f}s",
        )
        for lie in world.lies
        if not lie.refused
    ]
    return found


def _nothing_in_failsafe(world: World) -> list[Violation]:
    """Nothing reaches the vehicle or the camera from a failsafe until the operator's next
    resume (drone/safety.py): the mission does not silently fly on. The autopilot's own GCS
    failsafe counts from when the vehicle took itself over: the drone service was dead
    then, and the restarted one looks at the vehicle before it commands it."""
    vehicle, found = world.drone.vehicle, []
    starts = [*vehicle.failsafes, *((t, "autopilot GCS") for t in vehicle.gcs_failsafes)]
    for since, action in starts:
        until = min((t for t in vehicle.resumes if t >= since), default=float("inf"))
        found += _acted_between(world, "nothing-in-failsafe", f"{action} failsafe", since, until)
    return found


def _nothing_while_paused_or_ended(world: World) -> list[Violation]:
    """Nothing reaches the vehicle or the camera from an operator's pause until the next
    command that ends it (a resume, an abort, a land-now), nor ever after an abort or a
    land-now (drone/operator.py)."""
    found = []
    taken = world.drone.vehicle.operator
    for since, command, action in taken:
        if command == "pause":
            later = (t for t, c, _ in taken if t >= since and c != "pause")
            until = min(later, default=float("inf"))
            found += _acted_between(world, "nothing-while-paused", "pause", since, until)
        elif command in ("abort", "land_now"):
            what = f"{command} ({action})"
            found += _acted_between(world, "nothing-after-abort", what, since, float("inf"))
    return found


def _acted_between(
    world: World, oracle: str, what: str, since: float, until: float
) -> list[Violation]:
    """The oracle's violation if any request was acted on from ``since`` to ``until``."""
    drone = world.drone
    acted = [
        *drone.vehicle.commands,
        *drone.camera.pictures,
        *(a for reads in drone.vehicle.reads.values() for a in reads),
    ]
    inside = [a for a in acted if since <= a.time < until]
    if not inside:
        return []
    return [
        Violation(
            oracle,
            f"request {inside[0].reqnr} acted on at {inside[0].time:.3f}s, in the {what} "
            f"from {since:.3f}s, "
            + ("never ended" if until == float("inf") else f"ended at {until:.3f}s"),
        )
    ]


def _prepared_records(world: World) -> list[Violation]:
    """Every prepared handover's record is ``prepared`` or a forced fallback at its timeout."""
    found = []
    timeout = world.drone.prepare_timeout_s
    for r in world.drone.prepared_records:
        kind = label(drone_pb2.HandoverKind, r.kind)
        what = (
            f"handover {r.old_master}->{r.new_master} (epoch {r.epoch}) prepared from "
            f"{r.prepare_started_at:.3f}s to {r.decided_at:.3f}s: kind {kind!r}, "
            f"timed out {r.prepare_timed_out}, lacked {r.prepare_lacked_bytes} B"
        )
        if r.kind == drone_pb2.HANDOVER_KIND_PREPARED:
            ok = not r.prepare_timed_out and r.prepare_lacked_bytes <= PREPARED_BOUND_BYTES
        else:
            ok = (
                r.kind == drone_pb2.HANDOVER_KIND_COOPERATIVE
                and r.prepare_timed_out
                and r.decided_at >= r.prepare_started_at + timeout - 1e-9
            )
        if not ok:
            found.append(Violation("prepared-record", what))
    return found


def _at_most_once(world: World) -> list[Violation]:
    drone = world.drone
    acted = Counter(a.tag for a in (*drone.vehicle.commands, *drone.camera.pictures))
    found = [
        Violation("at-most-once", f"{tag!r} acted on {times} times")
        for tag, times in sorted(acted.items())
        if times > 1
    ]
    cut_reads = Counter(cut.reqnr for cut in drone.stats.cut_off)
    for reqnr, reads in sorted(drone.vehicle.reads.items()):
        if reqnr < 2**63 and len(reads) > 1 + cut_reads[reqnr]:
            found.append(
                Violation(
                    "at-most-once",
                    f"read of request {reqnr} executed {len(reads)} times "
                    f"({cut_reads[reqnr]} cut off by a drone restart)",
                )
            )
    return found


def _exactly_once(world: World) -> list[Violation]:
    drone = world.drone
    by_tag: dict[bytes, list[bytes]] = {}
    for acted in (*drone.vehicle.commands, *drone.camera.pictures):
        by_tag.setdefault(acted.tag, []).append(acted.reply)
    found = []
    reported: set[int] = set()
    for controller in world.incarnations:
        for index, (status, reply) in enumerate(controller.view):
            call = world.program[index]
            if status != 0 or not call.to_drone or index in reported:
                continue
            where = f"call {index} ({call.method}) answered OK at controller {controller.id}"
            if call.kind is Kind.BAD:
                problem = "a request the drone cannot parse"
            elif call.has_effect:
                replies = by_tag.get(call.request, [])
                problem = (
                    ""
                    if len(replies) == 1 and replies[0] == reply
                    else f"acted on {len(replies)} times, reply {'not ' * (reply not in replies)}"
                    "among the vehicle's"
                )
            else:
                reads = [r.reply for r in drone.vehicle.reads.get(call.reqnr, [])]
                problem = "" if reply in reads else f"reply not among the {len(reads)} reads"
            if problem:
                reported.add(index)
                found.append(Violation("exactly-once", f"{where}: {problem}"))
    return found


def _same_replies(world: World) -> list[Violation]:
    found = []
    observed = {id(c): _observed(c, world) for c in world.incarnations}
    longest_seen = max((c.seen[: observed[id(c)]] for c in world.incarnations), key=len)
    longest_view = max((c.view[: observed[id(c)]] for c in world.incarnations), key=len)
    for index, (reqnr, _, _) in enumerate(longest_seen):
        if reqnr != index + 1:
            found.append(Violation("same-replies", f"entry {index} is request {reqnr}"))
            break
    for controller in world.incarnations:
        name = f"controller {controller.id} (incarnation {controller.incarnation})"
        upto = observed[id(controller)]
        for what, mine, longest in (
            ("consumed entries", controller.seen[:upto], longest_seen),
            ("program answers", controller.view[:upto], longest_view),
        ):
            for k, item in enumerate(mine):
                if item != longest[k]:
                    found.append(
                        Violation(
                            "same-replies",
                            f"{name}: {what} differ at call {k}: {_brief(item)} vs "
                            f"{_brief(longest[k])}",
                        )
                    )
                    break
    return found


def _observed(controller: SimController, world: World) -> int:
    """How many of an incarnation's calls must match the others'.

    All of them, but for an incarnation a failover ended (its master lost,
    or fenced): only those consumed before the last request of it the drone
    accepted. What it consumed after that never left it (its Clock calls,
    its program's give-ups: decided where it ran), so nothing depends on
    it, and a taker may answer those calls otherwise. Everything before
    must match: the drone keeps the calls a master answered itself, sent
    along with its next request, the program's give-ups among them.

    The same for an incarnation killed while it held a log message that a
    takeover framed again in a newer epoch: alive, it would have rejoined
    with nothing (``Diverged``) before its program acted on anything after
    its last request the drone accepted, and been held to exactly that (a
    replica that consumed a give-up of a master cut off from the drone,
    killed before the taker's framing of that request reached it).

    And any killed incarnation is held to the calls up to the drone's last
    request when it died: above it, the drone had executed nothing, so what
    it consumed there were answers decided where they ran (a master's Clock
    reading or give-up, relayed or its own), which a taker may frame anew if
    they died with it; a dead incarnation acts on nothing. Whatever the live
    controllers consumed of the same calls is still compared.
    """
    if controller.ended_by or _would_have_rejoined(controller, world):
        return controller.accepted_upto
    died = controller.drone_last_at_death
    if died is not None and not controller.alive:
        return max(controller.accepted_upto, min(len(controller.seen), died))
    return len(controller.seen)


def _would_have_rejoined(controller: SimController, world: World) -> bool:
    """Killed (not ended by a failover) holding a log message of an older framing."""
    if controller.alive or controller.ended_by:
        return False
    protocol = controller.protocol
    for lognr, epochs in world.framings.items():
        ours = protocol.epoch_of(lognr)
        if ours and max(epochs) > ours:
            return True
    return False


def _brief(item: tuple[int | bytes, ...]) -> str:
    return repr(tuple(x[:40] if isinstance(x, bytes) else x for x in item))


def _failures(world: World) -> list[Violation]:
    found = [
        Violation("no-failure", c.failure) for c in world.incarnations if c.failure is not None
    ]
    for c in world.incarnations:
        # Nothing reached the vehicle, and the master sends it again for far longer than
        # any fault here lasts (the retry limit): no program is shown UNAVAILABLE.
        unavailable = [i for i, (status, _) in enumerate(c.view) if status == UNAVAILABLE]
        if unavailable:
            found.append(
                Violation(
                    "no-failure",
                    f"controller {c.id} (incarnation {c.incarnation}): the program was "
                    f"answered UNAVAILABLE at call {unavailable[0]}",
                )
            )
    return found


def _liveness(world: World) -> list[Violation]:
    found = []
    for controller in world.controllers.values():
        if controller.done_at is not None and controller.done_at <= world.deadline:
            continue
        if controller.id in world.lost:
            continue  # killed for good
        p = controller.protocol
        found.append(
            Violation(
                "liveness",
                f"controller {controller.id} not done by t={world.deadline:.1f}s "
                f"(faults ended at {world.plan.fault_end:.1f}s): program at call "
                f"{controller.pc}/{len(world.program)}, {p.state.name}, master={p.master}, "
                f"epoch {p.epoch}, reqnr {p.reqnr}, lognr {p.lognr}, queued "
                f"{sorted(p.log_queue)[:8]}, caught up {p.caught_up} "
                f"(to {p.catch_up_to}); drone master {world.drone.seq.master} "
                f"epoch {world.drone.seq.epoch} last reqnr {world.drone.seq.last_reqnr}; "
                f"waiting: {'; '.join(controller.holding().values()) or 'nothing it knows of'}",
            )
        )
    return found


def _bounded(world: World) -> list[Violation]:
    found = []
    for controller in world.controllers.values():
        if controller.id in world.lost:
            continue
        p = controller.protocol
        left = {
            "log queue": len(p.log_queue),
            "received beyond the watermark": len(p._received),
            "abandoned calls": len(controller.core.abandoned),
            "unflushed log entries": len(p.log),
        }
        for dest, link in sorted(controller.links.items()):
            if dest not in world.lost:  # kept for a peer that never comes back
                left[f"unacknowledged to {dest}"] = len(link.unacked)
        held = {what: n for what, n in left.items() if n}
        if held:
            found.append(Violation("bounded", f"controller {controller.id} still holds {held}"))
    drone = world.drone
    if drone.stats.peak_cache > drone.cache_window:
        found.append(
            Violation(
                "bounded",
                f"reply cache held {drone.stats.peak_cache} > window {drone.cache_window}",
            )
        )
    return found
