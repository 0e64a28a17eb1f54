"""The protocol's invariants as code, checked after every event of a run.

The oracles (``oracles.py``) judge a finished run; these judge every state
on the way, so a violation is reported at the event that made it, not at the
end (or never, if a later event hid it). Each invariant is a pure function of
the world's state (the controllers' ``ControllerProtocol``, the drone's
``Sequencer``, the ground truth ``SimVehicle`` and ``SimCamera``) and what
the ``Invariants`` checker remembers of the state before (for the ones about
never moving back), returning what is wrong or None. ``World`` installs the
checker as the loop's ``after_event`` hook; the first violation of each
invariant becomes a ``Violation`` naming it, the event number and the
virtual time, beside the oracles' (``python -m baton.sim --seed N`` prints
it with the replay line).

The invariants (docs/simulation.md, "Invariants"):

1. ``one-active-master-per-epoch``: no two live controllers ACTIVE as master
   in the same epoch. Not "at most one ACTIVE master": a master cut off
   from the drone and the ring stays ACTIVE in its own, older epoch until
   it hears of the takeover (docs/design.md, "Takeover"); what the protocol
   guarantees is that the epochs differ.
2. ``drone-one-master-per-epoch``: the drone never accepts requests of two
   controllers in one epoch (the end-of-run oracle's record, seen at once).
3. ``epoch-granted``: no controller's epoch is newer than the drone's: every
   epoch is the drone's grant.
4. ``drone-never-moves-back``: the drone's epoch, last request number and
   watermark never decrease, across drone restarts too (they are resumed
   from the store), and the watermark never passes the last request.
5. ``one-framing-per-epoch``: every log message sent with a log number and
   an epoch carries the same entries after the same request number (a
   master creates each number once in its epoch; forwards and re-sends copy
   it). So two controllers that hold number n in one epoch hold the same
   entries. Not the same origin: a taker that handed over last sends its
   own handover message on as a normal message of its own
   (``ControllerProtocol._resend_handed``), where the first copy named the
   lost new master as origin.
6. ``master-holds-the-ring-log``: whenever the drone accepts a new request,
   the master it serves (ACTIVE in the drone's epoch) holds at every log
   number it handled a framing no older than any live controller's, or one
   that shows the programs the same entries (a Clock.Sleep a lost master and
   its taker both framed: the epoch differs, not what was seen), or whose
   requests it holds, in whatever messages, with the outcomes the newer
   framing gives them (numbered otherwise, the same for every program:
   ``_agrees``), but
   those of masterships a takeover ended (the ring fences them: ``Fenced``;
   their holders rejoin). Not the newest ever sent (``World.framings``): a
   master lost mid-flush sends a framing that may reach nobody alive, and
   a taker may hold an older framing of a number the lost one framed again
   and died with. And not against a replaced mastership's: a taker whose
   own mastership a later takeover ended may hold an older, emptier
   framing of a number the replicas hold from that later master; it frames
   the same replies in its next message, and the replicas rejoin on it
   (``Diverged``). Not at every instant: a taker goes ACTIVE on the
   drone's grant, and then compares its framing with the replies the drone
   retained (``ControllerProtocol.replaced_framing``); one that holds a
   framing a later takeover replaced rejoins with nothing before it sends a
   request (ACTIVE so for the one event that finds it; the runs that found
   each case: docs/simulation.md, "Invariants"). With 5, a
   controller's handled log forks from the ring's only where it holds an
   older framing of a number that a takeover framed again; such a
   controller is a replaced master or a replica that handled its messages,
   and rejoins with nothing when the ring's message reaches it
   (``Diverged``), which ``oracles._observed`` allows for.
7. ``replies-held``: every entry a program consumed (a drone reply, a local
   answer, a give-up) is held by a live controller (handled, queued, in its
   history, or in a master's unflushed log) or by the drone (its reply cache,
   or the intent of a request a restart cut off, booked when it comes back),
   or the drone let it go because every controller held it (at or below its
   watermark).
   Only the entries the oracles hold an incarnation to
   (``oracles._observed``): what a failover-ended incarnation consumed
   after its last request the drone accepted never left it. Nor, of a killed
   incarnation, a local answer above the drone's last request: a taker may
   frame it anew, and the oracle then no longer holds the incarnation to it.
8. ``at-most-once``: no command or picture acted on twice at the vehicle
   (the oracle's count, at the event that broke it).
9. ``mastership-legal``: every live controller's masterships are a legal
   combination (``baton.controller.mastership.Mastership.problems``, which a
   running controller checks too with ``BATON_CHECK_INVARIANTS=1``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from baton.controller.core import CoreEffect
from baton.controller.protocol import SendLog, State, seen_as
from baton.drone.invariants import DroneWatch
from baton.sim.oracles import Violation, _observed
from baton.v1 import drone_pb2

if TYPE_CHECKING:
    from baton.sim.controller import SimController
    from baton.sim.world import World

INVARIANTS = (
    "one-active-master-per-epoch",
    "drone-one-master-per-epoch",
    "epoch-granted",
    "drone-never-moves-back",
    "one-framing-per-epoch",
    "master-holds-the-ring-log",
    "replies-held",
    "at-most-once",
    "mastership-legal",
)


@dataclass
class Before:
    """What the checker remembers of the drone between events."""

    watch: DroneWatch = field(default_factory=DroneWatch)
    conflicts: int = 0
    acted: int = 0


def one_active_master_per_epoch(live: list[SimController]) -> str | None:
    """No two live controllers ACTIVE as master in one epoch."""
    by_epoch: dict[int, int] = {}
    for c in live:
        p = c.protocol
        if p.state is State.ACTIVE and p.master:
            other = by_epoch.setdefault(p.epoch, c.id)
            if other != c.id:
                return f"controllers {other} and {c.id} both ACTIVE as master in epoch {p.epoch}"
    return None


def mastership_legal(live: list[SimController]) -> str | None:
    """Every live controller's masterships a legal combination (``Mastership.problems``)."""
    for c in live:
        mastership = c.protocol.mastership
        problems = mastership.problems()
        if problems:
            return f"controller {c.id}: {'; '.join(problems)} ({mastership})"
    return None


def drone_one_master_per_epoch(world: World, before: Before) -> str | None:
    """The drone accepted requests of one controller per epoch (its record grew no conflict)."""
    conflicts = world.drone.stats.epoch_conflicts
    if len(conflicts) > before.conflicts:
        before.conflicts = len(conflicts)
        return conflicts[-1]
    return None


def epoch_granted(world: World, live: list[SimController]) -> str | None:
    """No live controller is in an epoch newer than the drone's."""
    epoch = world.drone.seq.epoch
    for c in live:
        if c.protocol.epoch > epoch:
            return f"controller {c.id} in epoch {c.protocol.epoch}, the drone's is {epoch}"
    return None


def drone_never_moves_back(world: World, before: Before) -> str | None:
    """The drone's epoch, last reqnr and watermark never decrease; watermark <= last reqnr
    (``DroneWatch.moved``, the check a running drone makes too)."""
    seq = world.drone.seq
    return before.watch.moved(seq.epoch, seq.last_reqnr, seq.cache.watermark)


def master_holds_the_ring_log(world: World) -> str | None:
    """The drone's ACTIVE master holds the newest framing of every log number it handled
    (checked when the drone accepts a request: ``Invariants._master_log``)."""
    seq = world.drone.seq
    master = world.controllers.get(seq.master)
    if master is None or not master.alive:
        return None
    p = master.protocol
    if p.state is not State.ACTIVE or not p.master or p.epoch != seq.epoch:
        return None
    live = [c for c in world.live_controllers() if c is not master]
    # Masterships a takeover ended: their framings are fenced on the ring, not its log.
    replaced = {r.epoch - 1 for r in seq.handovers if r.kind == drone_pb2.HANDOVER_KIND_TAKEOVER}
    for lognr, epoch in p._epoch_at.items():
        if epoch >= max(world.framings.get(lognr, (epoch,))):
            continue  # the newest framing sent (the common case: nothing to look up)
        ours = _seen_in(master, lognr)
        for c in live:
            theirs = c.protocol.epoch_of(lognr)
            if theirs > epoch and theirs not in replaced:
                seen = _seen_in(c, lognr)
                if ours is not None and ours == seen:
                    continue  # framed again, the same for every program
                if seen is not None and _agrees(master, seen):
                    continue  # framed in other numbers, the same for every program
                return (
                    f"master {master.id} (epoch {p.epoch}) holds log message {lognr} of "
                    f"epoch {epoch}, controller {c.id} holds it of epoch {theirs}"
                )
    return None


def _agrees(master: SimController, seen: tuple[tuple[int, object], ...]) -> bool:
    """Whether every request of ``seen`` (``_seen_in``) the master holds, it holds with
    the same outcome: in a message it handled, queued or flushed, or in its unflushed
    log (a taker's retained replies). A request it lacks it has still to get."""
    p = master.protocol
    messages = [master.history.get(n) for n in master.history.above(0)]
    entries = [e for m in [*messages, *p.log_queue.values()] for e in m.entries]
    held = {e.reqnr: seen_as(e) for e in [*entries, *p.log.entries]}
    return all(held.get(reqnr, outcome) == outcome for reqnr, outcome in seen)


def _seen_in(c: SimController, lognr: int) -> tuple[tuple[int, object], ...] | None:
    """What the programs see of log message ``lognr`` as ``c`` holds it (in its history
    or queue): each entry's request number and outcome (``seen_as``); None if unknown."""
    message = c.protocol.log_queue.get(lognr)
    if message is None and lognr in c.history:
        message = c.history.get(lognr)
    if message is None:
        return None
    return tuple((entry.reqnr, seen_as(entry)) for entry in message.entries)


def replies_held(world: World, live: list[SimController]) -> str | None:
    """Every entry a program consumed is held by a live controller or by the drone."""
    seq = world.drone.seq
    # Every request up to a live controller's held_reqnr is held there.
    floor = max([seq.cache.watermark, *(c.protocol.held_reqnr for c in live)])
    consumed = max((len(c.seen) for c in world.incarnations), default=0)
    if consumed <= floor:
        return None
    # Beyond that: in a master's unflushed log, or in a log message received and queued
    # (a controller that restarted with nothing holds the ring's messages queued while
    # it replays the ones below).
    intent = world.drone.intent  # a request the drone executes, or a restart cut off
    unflushed = {e.reqnr for c in live for e in c.protocol.log.entries}
    unflushed.update(
        e.reqnr for c in live for m in c.protocol.log_queue.values() for e in m.entries
    )
    # A master's own flushed messages are in its history, not among those it handled.
    unflushed.update(
        e.reqnr for c in live for n in c.history.above(0) for e in c.history.get(n).entries
    )
    for c in world.incarnations:
        if len(c.seen) <= floor:
            continue
        upto = _observed(c, world)
        for reqnr, _, _ in c.seen[floor:upto]:
            if reqnr <= floor or reqnr in unflushed or seq.cache.get(reqnr) is not None:
                continue
            if intent is not None and intent.reqnr == reqnr:
                continue  # the drone's store keeps it: booked when the drone comes back
            if not c.alive and not c.ended_by and reqnr > seq.last_reqnr:
                # A killed program's local answer (a Clock reading, a give-up) that no
                # request took to the drone: a taker may frame it anew, and the oracle
                # then holds the killed incarnation only to what the drone accepted
                # (``oracles._would_have_rejoined``).
                continue
            return (
                f"request {reqnr}, consumed by controller {c.id} (incarnation "
                f"{c.incarnation}), is held by no live controller (they hold up to {floor}) "
                f"and not by the drone (watermark {seq.cache.watermark})"
            )
    return None


def at_most_once(world: World, before: Before) -> str | None:
    """No command or picture acted on twice (checked for the ones acted on since)."""
    drone = world.drone
    acted = [*drone.vehicle.commands, *drone.camera.pictures]
    if len(acted) == before.acted:
        return None
    before.acted = len(acted)
    tags = [a.tag for a in acted]
    if len(set(tags)) < len(tags):
        twice = sorted({t for t in tags if tags.count(t) > 1})
        return f"{twice[0]!r} acted on {tags.count(twice[0])} times"
    return None


class Invariants:
    """The checker a World installs: every invariant after every event (or every
    ``every``-th), the first violation of each kept."""

    def __init__(self, world: World, every: int = 1) -> None:
        self.world = world
        self.every = every
        self.before = Before()
        self.found: dict[str, Violation] = {}
        self.checks = 0
        b = self.before
        # Each check, and what it reads: it runs again only once that changed (a check
        # of a state it saw already would find the same), which keeps the checks after
        # every event affordable (docs/simulation.md, "Invariants").
        self._checks: tuple[tuple[str, Callable[[list[SimController]], str | None]], ...] = (
            ("one-active-master-per-epoch", one_active_master_per_epoch),
            ("epoch-granted", lambda live: epoch_granted(world, live)),
            ("replies-held", lambda live: replies_held(world, live)),
            ("mastership-legal", mastership_legal),
        )
        self._drone_checks: tuple[tuple[str, Callable[[], str | None]], ...] = (
            ("drone-one-master-per-epoch", lambda: drone_one_master_per_epoch(world, b)),
            ("drone-never-moves-back", lambda: drone_never_moves_back(world, b)),
            ("at-most-once", lambda: at_most_once(world, b)),
        )
        self._seen: tuple[object, ...] = ()
        self._drone_seen: tuple[object, ...] = ()
        # What master_holds_the_ring_log last looked at: checked again when it changes.
        self._master_seen: tuple[object, ...] = ()
        # One framing per (log number, epoch): what the first sent held (after_reqnr,
        # entries), and its origin.
        self._framed: dict[tuple[int, int], tuple[tuple[int, bytes], int]] = {}

    @property
    def violations(self) -> list[Violation]:
        """The first violation of each invariant, in the order found."""
        return list(self.found.values())

    def after_event(self) -> None:
        """The loop's hook: checks the state the event left."""
        loop = self.world.loop
        if loop.events % self.every:
            return
        self.checks += 1
        world = self.world
        drone = world.drone
        seq = drone.seq
        drone_key = (
            id(seq),
            len(seq.handovers),
            seq.last_reqnr,
            seq.cache.watermark,
            len(seq.cache),
            len(drone.vehicle.commands) + len(drone.camera.pictures),
            len(drone.stats.epoch_conflicts),
        )
        found = self.found
        if drone_key != self._drone_seen:
            self._drone_seen = drone_key
            for name, drone_check in self._drone_checks:
                if name not in found and (problem := drone_check()) is not None:
                    self._fail(name, problem)
        live = [c for c in world.controllers.values() if c.alive]
        key = (
            drone_key,
            len(world.incarnations),
            *[
                (
                    p,
                    p.state,
                    p.epoch,
                    p.master,
                    p.fenced,
                    p.granted_epoch,
                    p.held_reqnr,
                    len(c.seen),
                    len(p.log.entries),
                    len(p.log_queue),
                )
                for c in live
                for p in (c.protocol,)
            ],
        )
        if key != self._seen:
            self._seen = key
            for name, check in self._checks:
                if name not in found and (problem := check(live)) is not None:
                    self._fail(name, problem)
        if "master-holds-the-ring-log" not in found and (problem := self._master_log()):
            self._fail("master-holds-the-ring-log", problem)

    def _master_log(self) -> str | None:
        """Invariant 6, when the drone has accepted a new request."""
        world = self.world
        seq = world.drone.seq
        key = (id(seq), seq.last_reqnr)
        if key == self._master_seen:
            return None
        self._master_seen = key
        return master_holds_the_ring_log(world)

    def sent(self, controller: SimController, effects: Sequence[CoreEffect]) -> None:
        """``World.after_apply``'s hook: every log message sent keeps invariant 5."""
        if "one-framing-per-epoch" in self.found:
            return
        for effect in effects:
            if not isinstance(effect, SendLog):
                continue
            m = effect.message
            entries = b"".join(e.SerializeToString(deterministic=True) for e in m.entries)
            held = (m.after_reqnr, entries)
            first, origin = self._framed.setdefault((m.lognr, m.epoch), (held, m.origin))
            if first != held:
                self._fail(
                    "one-framing-per-epoch",
                    f"controller {controller.id} sent log message {m.lognr} of epoch {m.epoch} "
                    f"(origin {m.origin}, {len(m.entries)} entries after request "
                    f"{m.after_reqnr}) unlike the first sent with that number and epoch "
                    f"(origin {origin}, after request {first[0]})",
                )
                return

    def _fail(self, name: str, problem: str) -> None:
        loop = self.world.loop
        what = f"{problem} (after event {loop.events}, t={loop.now:.4f}s)"
        self.found[name] = Violation(name, what)
        self.world.trace(f"INVARIANT {name} broken: {what}")
