"""Every order of the events at small scope: breadth first, with state hashing.

``python -m baton.sim.explore --controllers 2 --calls 2 --fault drop``

The seeded runs (``world.py``) take one order of events per seed; this
takes every order, within a small world: 2 or 3 controllers, a mission of a
few flight commands, one scripted cooperative handover, and at most one
fault. It runs the same simulation (``World``: the controllers'
``ControllerProtocol``, the drone's ``Sequencer`` and ``DroneCore``, the
network, the drivers around them), with its scheduler made choosable: at
each step any *enabled* event may be taken next, and every choice is
explored. It checks the invariants (``invariants.py``) after every event
and the end-of-run oracles (``oracles.py``: every request executed exactly
once at the vehicle, every replica's program saw the same replies, the
mission completes, buffers drained) in every terminal state.

What is abstracted, and why:

- *Time, to a window.* Every link has the same latency, no jitter, no
  reordering within a stream, and unlimited bandwidth. An event is enabled
  when it is due within ``window`` seconds of the earliest pending one, and
  no earlier-scheduled event of the same handler on the same object is
  pending (a stream's frames, a link's timer, stay in order: a gRPC stream
  is FIFO). Taking a later event first runs it at its own time and the
  earlier ones late, at the time reached: so within the window, messages
  on different links are delivered in any order, and timers fire early or
  late relative to them. Beyond the window, time orders events as in a
  run (a takeover after 3 s without service is not raced against a 10 ms
  delivery; the seeded runs cover those with random delays).
- *A process's own wake-ups, first.* An event scheduled for the instant
  it was scheduled in (a controller's ``_pump``, a rejoin, the drone's
  wake of a stream) is taken next, alone: asyncio runs the callbacks made
  ready before it reads its sockets again, and one process's wake-up
  commutes with another's deliveries.
- *The start-up, in time order* (``Scope.from_start`` explores it too):
  the Connects, the grant and the ring's first streams until the programs
  start; the interleavings of interest come after.
- *The fault, to any moment.* The one fault is not timed: in every state
  until it is used, each of its forms is one more enabled event (kill a
  controller the mix may kill, restarted 0.5 s later; drop a ring stream
  or a drone connection that is up, which is what a lost message does in
  the simulation; deliver a pending log message twice; cut one controller
  from every other node for 0.5 s; restart the drone service 0.5 s later,
  from its store).
- *Random draws, to their middle* (``Midpoint``): a drawn duration (the
  vehicle's execution, a program's pause between calls, a reconnect
  delay) is the middle of its range, so that it does not depend on the
  order of the draws before it.
- *States, to a fingerprint* (``fingerprint``): what decides the future
  of each controller's protocol (state, mastership, epoch, numbers, queue,
  what it received), its program's progress, its links' and session's
  state, the drone's sequencer (master, epoch, numbers, cache, owed
  notices, queue) and the vehicle's count, and the pending events (kind,
  owner, time from now, arguments in brief). Two states with one
  fingerprint are explored once. Left out: back-off lengths and reply
  bytes (a read's holds the time): a pruned state may differ in those,
  which the abstraction takes to not matter. Connection generations and
  session ids are in (as event arguments): they keep apart states that
  may be the same, which costs time, not coverage.
- *Re-execution, not snapshots.* A state is the list of choices that
  reached it; expanding it builds the world again and replays them (the
  world holds SQLite history files, which cannot be copied). Deterministic:
  the same choices reach the same state.
"""

from __future__ import annotations

import argparse
import hashlib
import random
import sys
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from google.protobuf.message import DecodeError

from baton.drone.dedupe import DEFAULT_WINDOW
from baton.drone.sequencer import ScriptedHandover
from baton.sim.faults import FaultPlan, drone_crash, killable, partition
from baton.sim.loop import Event
from baton.sim.mission import COMMANDS, Kind, MissionCall
from baton.sim.mutations import MUTATIONS, mutated
from baton.sim.network import LinkSpec, RingLink
from baton.sim.oracles import Violation
from baton.sim.world import SimOptions, World
from baton.v1 import ring_pb2

if TYPE_CHECKING:
    from baton.sim.network import Network

FAULTS = ("none", "kill", "drop", "dup", "partition", "drone-restart")
# The time a killed controller stays down, and a partition lasts.
DOWN_S = 0.5
# A run that has not ended by then (virtual seconds) or this many events is a stall.
END_S = 120.0
END_EVENTS = 20_000


@dataclass(frozen=True)
class Scope:
    """The small world explored: its size, its handover and its fault."""

    controllers: int = 2
    calls: int = 2
    # A scripted cooperative handover to controller 1 after this request (0: none).
    handover_after: int = 1
    fault: str = "none"
    # Events due within this many seconds of the earliest pending one may go first.
    window: float = 0.01
    # Every link's latency, seconds.
    latency: float = 0.01
    flush_limit: int = 0
    # Explore the start-up too (the Connects, the grant, the ring's first streams);
    # False: taken in time order until the programs start.
    from_start: bool = False

    def describe(self) -> str:
        """The scope in a line."""
        handover = f"handover 0->1 after request {self.handover_after}"
        return (
            f"{self.controllers} controllers, {self.calls} calls, "
            f"{handover if self.handover_after else 'no handover'}, fault {self.fault}, "
            f"window {self.window * 1000:g} ms, latency {self.latency * 1000:g} ms"
        )

    def shape(self, world: World) -> tuple[dict[int, ScriptedHandover], int]:
        """``World``'s hook before the network is built: the ring, the flush limit, the
        program of flight commands and the script; returns the script and cache window."""
        world.ring = list(range(self.controllers))
        world.flush_limit = self.flush_limit
        world.program = tuple(
            MissionCall(i, Kind.COMMAND, COMMANDS[i % len(COMMANDS)], b"command #%d" % i)
            for i in range(self.calls)
        )
        script = {}
        if self.handover_after:
            script[self.handover_after] = ScriptedHandover(self.handover_after, 1, 1)
        return script, DEFAULT_WINDOW

    def quiet(self, world: World) -> FaultPlan:
        """``World``'s hook for the fault plan: no random fault, equal links, no jitter."""
        net: Network = world.net
        for key, spec in net.specs.items():
            net.specs[key] = LinkSpec(self.latency, float("inf"), 0.0, False)
            del spec
        net.p_loss = net.p_dup = 0.0
        world.faulty = False
        world.drone.p_ack_lost = 0.0
        world.rng = Midpoint()
        return FaultPlan(fault_end=0.0)


class Midpoint(random.Random):
    """The explored world's random stream: every draw the middle of its range (a
    duration drawn from 0.1 to 0.3 s is 0.2 s), so that no draw depends on the
    order of the draws before it, which the order of events changes."""

    def random(self) -> float:
        return 0.5

    def _randbelow(self, n: int) -> int:  # type: ignore[override]
        return n // 2


@dataclass(frozen=True)
class Choice:
    """One enabled step: a pending event, or a form of the fault."""

    label: str
    event: Event | None = None
    fault: Callable[[World], None] | None = None


def _owner(callback: Callable[..., None]) -> object:
    return getattr(callback, "__self__", None)


def enabled(
    world: World, scope: Scope, fault_used: bool, immediate: set[int] | None = None
) -> list[Choice]:
    """The events that may be taken next, then the fault's forms (until it is used).

    An event scheduled for the instant it was scheduled in (``immediate``: a
    wake-up on the next turn of a process's loop) goes first, alone."""
    pending = world.loop.pending()
    choices: list[Choice] = []
    if immediate:
        for event in pending:
            if event[1] in immediate:
                return [Choice(_describe(event), event=event)]
    if pending:
        first = pending[0][0]
        held: set[tuple[int, Any]] = set()
        for event in pending:
            when, _, callback, _args = event
            if when > first + scope.window:
                break
            key = (id(_owner(callback)), getattr(callback, "__func__", callback))
            if key in held:
                continue
            held.add(key)
            choices.append(Choice(_describe(event), event=event))
    if not fault_used and world.programs_started and world.mission_open():
        choices += _fault_forms(world, scope)
    return choices


def _fault_forms(world: World, scope: Scope) -> list[Choice]:
    forms: list[Choice] = []
    live = world.live_controllers()
    if scope.fault == "kill":
        for c in live:
            if killable(world, c):
                forms.append(Choice(f"kill {c.id}", fault=_kill(c.id)))
    elif scope.fault == "drop":
        for c in live:
            for dest, link in sorted(c.links.items()):
                if link.up:
                    forms.append(Choice(f"drop ring {c.id}->{dest}", fault=_drop_ring(c.id, dest)))
            if c.drone_link.usable():
                forms.append(Choice(f"drop drone link of {c.id}", fault=_drop_drone(c.id)))
    elif scope.fault == "dup":
        for event in world.loop.pending():
            if _is_message_frame(event):
                forms.append(Choice(f"twice: {_describe(event)}", fault=_duplicate(event)))
    elif scope.fault == "partition":
        for c in live:
            forms.append(Choice(f"partition {c.id}", fault=_partition(c.id)))
    elif scope.fault == "drone-restart" and world.drone.up:
        forms.append(Choice("drone restarts", fault=_drone_restart))
    return forms


def _kill(cid: int) -> Callable[[World], None]:
    def act(world: World) -> None:
        world.controller(cid).kill("killed (explore)")
        world.loop.after(DOWN_S, world.restart_controller, cid)

    return act


def _drop_ring(cid: int, dest: int) -> Callable[[World], None]:
    return lambda world: world.controller(cid).links[dest].break_("dropped (explore)")


def _drop_drone(cid: int) -> Callable[[World], None]:
    return lambda world: world.controller(cid).drone_link.break_("dropped (explore)")


def _drone_restart(world: World) -> None:
    drone_crash(world, world.loop.now + DOWN_S)


def _duplicate(event: Event) -> Callable[[World], None]:
    return lambda world: world.loop.push(event)


def _partition(cid: int) -> Callable[[World], None]:
    return lambda world: partition(world, [cid], world.loop.now + DOWN_S)


def _is_message_frame(event: Event) -> bool:
    _, _, callback, args = event
    return (
        getattr(callback, "__func__", None) is RingLink._arrive
        and len(args) == 3
        and getattr(args[1], "__func__", None) is RingLink._message_frame
    )


def _describe(event: Event) -> str:
    when, _, callback, args = event
    name = getattr(callback, "__qualname__", repr(callback))
    owner = _owner(callback)
    who = getattr(owner, "id", None)
    if who is None:
        who = getattr(getattr(owner, "owner", None), "id", None)
    dest = getattr(owner, "dest", None)
    where = f" {who}" + (f"->{dest}" if dest is not None else "")
    inner = ""
    for arg in args:
        if callable(arg):
            inner = f" {getattr(arg, '__qualname__', '')}"
    return f"{name}{where if who is not None else ''}{inner} @{when:.4f}"


# -- fingerprints -----------------------------------------------------------------------


def _brief(value: object, now: float) -> object:
    """An event argument, in brief: what it is, not where it lives."""
    if isinstance(value, bool | int | str) or value is None:
        return value
    if isinstance(value, float):
        return round(value, 6)
    if isinstance(value, bytes):
        try:
            message = ring_pb2.LogMessage.FromString(value)
            return ("log", message.lognr, message.epoch, message.origin, message.handover)
        except DecodeError:  # not a log message: its digest
            return hashlib.sha256(value).hexdigest()[:12]
    if isinstance(value, ring_pb2.LogMessage):
        return ("log", value.lognr, value.epoch, value.origin, value.handover)
    if isinstance(value, tuple | list):
        return tuple(_brief(v, now) for v in value)
    if callable(value):
        return getattr(value, "__qualname__", type(value).__name__)
    cid = getattr(value, "id", None)
    return (type(value).__name__, cid if isinstance(cid, int) else None)


def fingerprint(world: World, fault_used: bool) -> str:
    """What decides the future of ``world``, hashed (time as time from now)."""
    now = world.loop.now
    parts: list[object] = [fault_used, world.programs_started]
    for cid, c in sorted(world.controllers.items()):
        p = c.protocol
        parts.append(
            (
                cid,
                c.incarnation,
                c.alive,
                p.state.name,
                p.master,
                p.epoch,
                p.granted_epoch,
                p.reqnr,
                p.lognr,
                p.held_reqnr,
                p.watermark_reqnr,
                p.fenced,
                p.catch_up_to,
                tuple((n, m.epoch, m.origin) for n, m in sorted(p.log_queue.items())),
                (p._received.upto, tuple(sorted(p._received.above))),
                tuple(sorted(p._epoch_at.items())),
                len(p.log),
                (c.pc, c.waits_for, c.answering, len(c.seen), c.done, c.failure),
                (c.session is not None and c.session.connected, c.answered),
                tuple(
                    (d, link.up, tuple(sorted(link.unacked)), round(link._fifo - now, 6))
                    for d, link in sorted(c.links.items())
                ),
            )
        )
    drone = world.drone
    seq = drone.seq
    parts.append(
        (
            drone.up,
            seq.master,
            seq.epoch,
            seq.last_reqnr,
            seq.cache.watermark,
            tuple(seq.cache.reqnrs),
            tuple(sorted(seq.pending)),
            tuple(type(item).__name__ for item in drone.queue),
            drone.busy is not None,
            tuple(sorted(drone.streams)),
            len(drone.vehicle.commands),
        )
    )
    events = sorted(
        (
            round(when - now, 6),
            getattr(callback, "__qualname__", ""),
            _brief(_owner(callback), now),
            _brief(args, now),
        )
        for when, _, callback, args in world.loop.pending()
    )
    parts.append(tuple(repr(e) for e in events))
    return hashlib.sha256(repr(parts).encode()).hexdigest()


# -- the search ---------------------------------------------------------------------


@dataclass
class Found:
    """A terminal state whose oracles or invariants failed, and the choices to it."""

    violations: list[Violation]
    path: list[str]

    def report(self) -> str:
        """The violations and the steps chosen (labels of the choices made)."""
        lines = [str(v) for v in self.violations]
        lines.append(f"  after {len(self.path)} choices:")
        lines += [f"    {step}" for step in self.path]
        return "\n".join(lines)


@dataclass
class Exploration:
    """What a search saw."""

    scope: Scope
    states: int = 0  # choice points reached (expanded or pruned)
    distinct: int = 0  # distinct fingerprints expanded
    terminal: int = 0  # runs that ended (every event taken)
    events: int = 0  # events taken, over every re-execution
    depth: int = 0  # the most choices on one path
    seconds: float = 0.0
    found: list[Found] = field(default_factory=list)
    complete: bool = True  # False: stopped at max_states

    def summary(self) -> str:
        """The figures in a line."""
        return (
            f"{self.scope.describe()}: {self.states} states reached, {self.distinct} distinct, "
            f"{self.terminal} terminal, depth {self.depth}, {self.events} events taken, "
            f"{self.seconds:.1f} s{'' if self.complete else ' (stopped at the state bound)'}; "
            f"{len(self.found)} failing"
        )


@dataclass
class _Reached:
    """Where replaying a path ended: a choice point, or the end of the run."""

    world: World
    choices: list[Choice]
    labels: list[str]
    fault_used: bool
    ended: bool


def _replay(scope: Scope, path: Sequence[int], options: SimOptions) -> _Reached:
    """Builds the world and takes ``path``'s choices; runs on to the next choice point."""
    world = World(0, options, scope)
    world.begin()
    fault_used = False
    labels: list[str] = []
    step = 0
    loop = world.loop
    # Events scheduled for the instant they were scheduled in, not taken yet.
    immediate: set[int] = set()
    while True:
        if world.invariants is not None and world.invariants.found:
            return _Reached(world, [], labels, fault_used, True)
        if loop.now > END_S or loop.events > END_EVENTS:
            return _Reached(world, [], labels, fault_used, True)
        choices = enabled(world, scope, fault_used, immediate)
        if not scope.from_start and not world.programs_started:
            choices = choices[:1]
        if not choices:
            return _Reached(world, [], labels, fault_used, True)
        if len(choices) == 1:
            chosen = choices[0]
            if chosen.fault is not None:
                labels.append(chosen.label)
        elif step == len(path):
            return _Reached(world, choices, labels, fault_used, False)
        else:
            chosen = choices[path[step]]
            step += 1
            labels.append(chosen.label)
        last = loop.scheduled
        if chosen.event is not None:
            immediate.discard(chosen.event[1])
            loop.take(chosen.event)
        else:
            assert chosen.fault is not None
            fault_used = True
            chosen.fault(world)
        immediate.update(e[1] for e in loop.pending() if e[1] > last and e[0] <= loop.now)


def explore(
    scope: Scope,
    max_states: int = 1_000_000,
    stop_at_first: bool = True,
    options: SimOptions | None = None,
) -> Exploration:
    """Breadth first over every order of the enabled events of ``scope``'s world."""
    options = options or SimOptions()
    result = Exploration(scope)
    started = time.perf_counter()
    seen: set[str] = set()
    frontier: deque[tuple[int, ...]] = deque([()])
    while frontier:
        path = frontier.popleft()
        reached = _replay(scope, path, options)
        world = reached.world
        try:
            result.events += world.loop.events
            result.depth = max(result.depth, len(path))
            if reached.ended:
                result.terminal += 1
                violations = world.verdict()
                if violations:
                    result.found.append(Found(violations, reached.labels))
                    if stop_at_first:
                        break
                continue
            result.states += 1
            key = fingerprint(world, reached.fault_used)
            if key in seen:
                continue
            seen.add(key)
            result.distinct += 1
            if result.distinct >= max_states:
                result.complete = False
                break
            frontier.extend((*path, i) for i in range(len(reached.choices)))
        finally:
            world.close()
    result.seconds = time.perf_counter() - started
    return result


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m baton.sim.explore``: one scope; 1 if a terminal state failed."""
    p = argparse.ArgumentParser(
        prog="python -m baton.sim.explore",
        description="every order of the events at small scope (breadth first, state hashing)",
    )
    p.add_argument("--controllers", type=int, default=2, choices=(2, 3))
    p.add_argument("--calls", type=int, default=2)
    p.add_argument("--handover-after", type=int, default=1, help="request number (0: none)")
    p.add_argument("--fault", choices=FAULTS, default="none")
    p.add_argument("--window-ms", type=float, default=10.0)
    p.add_argument("--max-states", type=int, default=1_000_000)
    p.add_argument("--mutation", choices=sorted(MUTATIONS), help="put a known defect back")
    p.add_argument("--all", action="store_true", help="go on past the first failing state")
    p.add_argument(
        "--kill-master", action="store_true", help="the kill may hit a master in any sense"
    )
    args = p.parse_args(argv)
    scope = Scope(
        controllers=args.controllers,
        calls=args.calls,
        handover_after=args.handover_after,
        fault=args.fault,
        window=args.window_ms / 1000,
    )
    with mutated(args.mutation):
        options = SimOptions(kill_master=args.kill_master)
        result = explore(scope, args.max_states, not args.all, options)
    for found in result.found:
        print(found.report())
    print(result.summary(), file=sys.stderr)
    return 1 if result.found else 0


if __name__ == "__main__":
    sys.exit(main())
