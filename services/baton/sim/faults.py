"""The faults of one seed: what breaks, when, and for how long.

Everything is drawn from the seed when the world is built, except whom a
kill or a give-up hits, which is drawn when it happens (from the same
random stream, so a seed still replays exactly). Every fault starts and
ends inside the fault window ``[0, fault_end]``; after it the network
delivers everything, every part is up, and the oracles expect the
mission to finish (liveness).

The default mix (each seed draws its own counts and odds):

- messages: per-message loss (the stream resets and the ring re-sends
  after the reconnect's hello and sync), duplicates, reordering on some
  directions, slow and asymmetric directions (``network.Network``);
- link drops (a ring stream or a drone connection) and partitions (a group
  of nodes, the drone possibly among them, cut from the rest);
- kills of a controller that is not master in any sense, restarted with
  nothing after a while (``killable``); killing the master is issue 10
  (failover) and only in the mix with ``kill_master`` (expect stalls);
- drone service restarts (durable state kept, calls in flight lost);
- vehicle outages (Mobility calls UNAVAILABLE, re-sent by the master);
- commands whose acknowledgement the vehicle never sends (executed,
  DEADLINE_EXCEEDED);
- the mission program giving up on a call: the master's call while it is
  still the master's to log, or a replica's held call whose give-up the
  master logged (anything else makes the mission non-deterministic by
  design: docs/design.md, "Exactly once when callers give up");
- Handover calls at random moments (``ready_for_handover``), some there
  and back, one at the end of the mission, besides the drone's scripted
  handovers (``World``);

Where a known finding (findings.py) would strike, the default mix waits
or leaves the fault out; ``SimOptions.allow`` lets it in.
- one garbled Invoke in the master's name and epoch with a request number
  far ahead (what MAX_REQNR_GAP is for).
"""

from __future__ import annotations

import random
from dataclasses import dataclass
from typing import TYPE_CHECKING

import grpc

from baton.controller.protocol import State
from baton.sim.drone import HandoverOrder, Request
from baton.sim.lying import plan_lying
from baton.sim.mission import GET_POSITION
from baton.sim.network import DRONE

if TYPE_CHECKING:
    from baton.sim.controller import SimController
    from baton.sim.world import World

GIVE_UP_CODES = (grpc.StatusCode.CANCELLED, grpc.StatusCode.DEADLINE_EXCEEDED)


@dataclass
class FaultPlan:
    """How many faults of each kind this seed has (for the report)."""

    fault_end: float
    drops: int = 0
    partitions: int = 0
    kills: int = 0
    drone_restarts: int = 0
    outages: int = 0
    give_ups: int = 0
    handovers: int = 0
    back_to_back: int = 0
    end_handover: bool = False
    garbled: bool = False
    lose_master: str = ""
    lying: str = ""
    stall: str = ""
    failsafe: str = ""
    operator: str = ""
    autopilot: str = ""

    def describe(self) -> str:
        """One line: the counts that are not zero."""
        parts = [f"window {self.fault_end:.1f}s"]
        for name in (
            "drops",
            "partitions",
            "kills",
            "drone_restarts",
            "outages",
            "give_ups",
            "handovers",
            "back_to_back",
        ):
            count = getattr(self, name)
            if count:
                parts.append(f"{name} {count}")
        if self.end_handover:
            parts.append("handover at the end")
        if self.garbled:
            parts.append("garbled request")
        if self.lose_master:
            parts.append(f"lose master: {self.lose_master}")
        if self.stall:
            parts.append(f"stall: {self.stall}")
        if self.failsafe:
            parts.append(f"failsafe: {self.failsafe}")
        if self.operator:
            parts.append(f"operator: {self.operator}")
        if self.lying:
            parts.append(f"lying: {self.lying}")
        if self.autopilot:
            parts.append(f"autopilot: {self.autopilot}")
        return ", ".join(parts)


def plan_faults(world: World) -> FaultPlan:
    """Draws this seed's faults and schedules them on the world's loop."""
    rng, loop = world.rng, world.loop
    end = rng.uniform(1.0, 6.0)
    plan = FaultPlan(end)

    def when() -> float:
        return rng.uniform(0.0, end)

    def until(start: float, longest: float) -> float:
        return min(end, start + rng.uniform(0.02, longest))

    plan.drops = rng.choice((0, 0, 1, 2, 4, 8))
    for _ in range(plan.drops):
        loop.at(when(), drop_link, world)
    plan.partitions = rng.choice((0, 0, 1, 2))
    nodes = [*world.ring, DRONE]
    for _ in range(plan.partitions):
        group = rng.sample(nodes, rng.randint(1, max(1, len(nodes) // 2)))
        start = when()
        loop.at(start, partition, world, group, until(start, 2.0))
    plan.kills = rng.choice((0, 0, 1, 1, 2, 3))
    for _ in range(plan.kills):
        start = when()
        loop.at(start, kill, world, until(start, 2.0))
    plan.drone_restarts = rng.choice((0, 0, 0, 1, 2))
    for _ in range(plan.drone_restarts):
        start = when()
        loop.at(start, drone_crash, world, until(start, 1.0))
    plan.outages = rng.choice((0, 0, 1, 2))
    for _ in range(plan.outages):
        start = when()
        loop.at(start, vehicle_outage, world, until(start, 1.5))
    plan.give_ups = rng.choice((0, 0, 1, 3, 6))
    for _ in range(plan.give_ups):
        loop.at(when(), give_up, world, rng.choice(GIVE_UP_CODES))
    plan.handovers = rng.choice((0, 1, 2, 4, 6))
    ids = world.ring
    for _ in range(plan.handovers):
        start, target = rng.uniform(0.0, end * 1.5), rng.choice(ids)
        if rng.random() < 0.3:  # back to back: away and straight back
            plan.back_to_back += 1
            loop.at(start, there_and_back, world, target, rng.uniform(0.0, 0.005))
        else:
            loop.at(start, handover, world, target)
    plan.end_handover = rng.random() < 0.3
    plan.garbled = rng.random() < 0.1
    if plan.garbled:
        loop.at(when(), garbled_request, world)
    loop.at(end, faults_stop, world)
    if world.options.lose_master:
        plan_failover(world, plan)
    if world.options.stall_new_master:
        plan_stall(world, plan)
    if world.options.failsafe:
        plan_failsafe(world, plan)
    if world.options.operator:
        plan_operator(world, plan)
    if world.options.lying:
        plan_lying(world, plan)
    if world.options.autopilot:
        plan_autopilot(world, plan)
    return plan


# The operator's commands the --operator scenario draws from: a pause then a resume,
# a pause then an abort, an abort, a land-now.
OPERATOR_PLANS = ("pause, resume", "pause, resume", "pause, abort", "abort", "land_now")


def plan_operator(world: World, plan: FaultPlan) -> None:
    """The operator-command fault (issue 32, item 4), from a random stream of its own: at
    a drawn moment an operator pauses the mission and resumes it 0 to 3 s later (or
    aborts it instead), aborts it (rtl or land), or lands the vehicle now."""
    rng = random.Random(f"operator {world.seed}")
    kind = rng.choice(OPERATOR_PLANS)
    start = rng.uniform(0.0, plan.fault_end)
    action = rng.choice(("rtl", "land"))
    first, _, then = kind.partition(", ")
    steps = [(first, 0.0)] + ([(then, rng.uniform(0.0, 3.0))] if then else [])
    plan.operator = f"{first} at {start:.2f}s" + (
        f", {then} {steps[1][1]:.2f}s later" if then else ""
    )
    if "abort" in kind:
        plan.operator += f" (abort: {action})"
    world.loop.at(start, operator_commands, world, steps, action)


def operator_commands(world: World, steps: list[tuple[str, float]], action: str) -> None:
    """An operator's commands in turn (Drone.Pause, Resume, Abort, LandNow), each the
    drawn delay after the one before went through: a call is sent again every 0.1 s
    while the drone is down (it fails UNAVAILABLE), as a person would."""
    if not world.drone.up:
        world.loop.after(0.1, operator_commands, world, steps, action)
        return
    (command, _), rest = steps[0], steps[1:]
    world.trace(f"operator: {command} {action if command == 'abort' else ''}".rstrip())
    world.drone.operator_rpc(command, action)
    if rest:
        world.loop.after(rest[0][1], operator_commands, world, rest, action)


# The modes the autopilot takes the vehicle into (--autopilot), as MAVSDK names them: its
# own return (fence, battery, GCS failsafe), its own landing, a pilot's position mode.
AUTOPILOT_MODES = ("RETURN_TO_LAUNCH", "LAND", "POSCTL")


def plan_autopilot(world: World, plan: FaultPlan) -> None:
    """The autopilot-takeover fault (issue 32), from a random stream of its own: at a
    drawn moment the vehicle switches to a drawn mode the drone did not command, and in
    half the seeds an operator's Resume comes 0 to 3 s later; and, from the GCS
    failsafe's stream, in half the seeds the drone service dies for longer or shorter
    than the autopilot's GCS failsafe time (``SimVehicle.gcs_failsafe``)."""
    rng = random.Random(f"autopilot {world.seed}")
    mode = rng.choice(AUTOPILOT_MODES)
    start = rng.uniform(0.0, plan.fault_end)
    plan.autopilot = f"{mode} at {start:.2f}s"
    world.loop.at(start, autopilot_takes_over, world, mode)
    if rng.random() < 0.5:
        resume_at = start + rng.uniform(0.0, 3.0)
        plan.autopilot += f", resumed at {resume_at:.2f}s"
        world.loop.at(resume_at, operator_resume, world)
    # The drone service dead for 0.5 to 2.5 times the autopilot's GCS failsafe time in
    # half the seeds (the mix's drone restarts may outlast it too): the vehicle returns
    # and lands by itself, and the restarted drone must end the mission.
    grng = world.gcs_rng
    timeout = world.autopilot_gcs_timeout
    plan.autopilot += f", GCS failsafe after {timeout:.2f}s"
    if grng.random() < 0.5:
        dead = timeout * grng.uniform(0.5, 2.5)
        start = grng.uniform(0.0, plan.fault_end)
        plan.autopilot += f", drone dead {dead:.2f}s at {start:.2f}s"
        world.loop.at(start, drone_crash, world, start + dead)


def autopilot_takes_over(world: World, mode: str) -> None:
    """The vehicle switches to ``mode`` on the autopilot's own decision."""
    world.trace(f"the autopilot takes the vehicle over: {mode}")
    world.drone.vehicle.take_over(world.loop.now, mode)


def plan_failsafe(world: World, plan: FaultPlan) -> None:
    """The every-station-lost fault (issue 32), from a random stream of its own: from a
    drawn moment every controller is cut from the drone for 0.5 to 2.5 times lost_link
    (so in most seeds the drone's failsafe acts), and in half the seeds an operator's
    Resume comes at a drawn moment after the cut heals."""
    rng = random.Random(f"failsafe cut {world.seed}")
    lost_link = world.safety.lost_link_s
    length = lost_link * rng.uniform(0.5, 2.5)
    start = rng.uniform(0.0, plan.fault_end)
    plan.failsafe = f"every station cut for {length:.2f}s (lost_link {lost_link:g}s, " + (
        f"{world.safety.lost_link_action})"
    )
    world.loop.at(start, cut_every_station, world, length)
    if world.battery_drain:
        reserve_at = (100.0 - world.safety.battery_reserve_pct) / world.battery_drain
        plan.failsafe += f", battery at the reserve at {reserve_at:.2f}s"
    if rng.random() < 0.5:
        resume_at = start + length + rng.uniform(0.0, 2.0 * lost_link)
        plan.failsafe += f", resumed at {resume_at:.2f}s"
        world.loop.at(resume_at, operator_resume, world)


def cut_every_station(world: World, length: float) -> None:
    """Partitions every controller from the drone for ``length`` seconds."""
    world.trace(f"every station cut from the drone for {length:.3f}s")
    pairs = [(cid, DRONE) for cid in world.ring]
    for a, b in pairs:
        world.net.cut(a, b)
    world.loop.after(length, heal, world, pairs)


def operator_resume(world: World) -> None:
    """The operator's Resume (Drone.Resume), whether or not the vehicle is in failsafe."""
    world.trace("operator resumes")
    world.drone.operator_rpc("resume")


LOSE_MODES = ("any time", "mid-flush", "after handover", "drone link cut")


def plan_failover(world: World, plan: FaultPlan) -> None:
    """The lose-master fault (issue 10), drawn from the world's failover stream.

    One of: the drone's master killed for good at a random moment; killed
    for good right after it sent a log message (the message in flight or
    just delivered); the old or the new master of a cooperative handover
    killed for good right after the drone decided it (before or after its
    notice and log left); or the master's drone link cut for a while,
    shorter or longer than the takeover time (it lives on and is fenced).
    """
    rng, end = world.frng, plan.fault_end
    mode = rng.choice(LOSE_MODES)
    start = rng.uniform(0.0, end)
    if mode == "after handover":
        plan.lose_master = f"{mode} ({rng.choice(('old', 'new'))} master)"
        strike = "old" if "old" in plan.lose_master else "new"
        world.loop.at(start, _arm, world, "on switch", strike)
    elif mode == "mid-flush":
        plan.lose_master = mode
        world.loop.at(start, _arm, world, "on flush", True)
    elif mode == "drone link cut":
        length = world.takeover_after * rng.uniform(0.5, 3.0)
        plan.lose_master = f"{mode} for {length:.2f}s"
        world.loop.at(start, cut_master, world, length)
    else:
        plan.lose_master = mode
        world.loop.at(start, lose_master, world)


def plan_stall(world: World, plan: FaultPlan) -> None:
    """The stall fault, from a random stream of its own (every other draw of the seed
    stays where it was): from a drawn moment, the next cooperative switch cuts the ring
    from its new master for 0.5 to 3 times how long the drone lets a master go without
    serving (``DroneCore.serve_within_s``); the new master's drone link stays up."""
    rng = random.Random(f"stall {world.seed}")
    length = world.drone.core.serve_within_s * rng.uniform(0.5, 3.0)
    plan.stall = f"the ring cut from a new master for {length:.2f}s"
    world.loop.at(rng.uniform(0.0, plan.fault_end), _arm, world, "stall on switch", length)


def stall_ring(world: World, new_master: int, length: float) -> None:
    """Cuts every ring link into and out of ``new_master`` for ``length`` seconds."""
    pairs = [(cid, new_master) for cid in world.ring if cid != new_master]
    world.trace(f"ring cut from new master {new_master} for {length:.3f}s")
    for a, b in pairs:
        world.net.cut(a, b)
    world.loop.after(length, heal, world, pairs)


def _arm(world: World, trigger: str, value: object) -> None:
    world.failover[trigger] = value


def lose_master(world: World, tries: int = 0) -> None:
    """Kills the drone's master for good, once the programs run and it is survivable
    (tried every 50 ms for up to 5 s, else the master is not lost)."""
    if world.programs_started and survivable(world, world.drone.seq.master):
        world.lose(world.drone.seq.master, "master")
    elif tries < 100:
        world.loop.after(0.05, lose_master, world, tries + 1)


def survivable(world: World, victim: int) -> bool:
    """Whether losing ``victim`` for good leaves a live copy of the log: another live
    controller holds every request the drone no longer retains for a taker.

    The drone retains the replies above its watermark (all it holds, after a
    restart: the watermark is not stored); the others exist only on the
    ring. The watermark says what the ring held when the master last heard,
    but the mix's kills restart a controller *with
    nothing* (a controller without a durable log file): one killed since
    then, or killed before and not caught up yet, holds none of it. Losing
    the master for good on top of that is two faults where every copy of
    the log is gone, which no design survives (one live holder is the
    least failover needs; a durable ``--log-file`` is what makes a kill
    keep its copy). So the lose-master fault waits until a live holder
    exists, as the kills wait for what a restart needs (``killable``).
    """
    seq = world.drone.seq
    retained = {reply.reqnr for reply in seq.cache.retained_replies()}
    needed = set(range(1, seq.last_reqnr + 1)) - retained
    if not needed:
        return True
    for c in world.live_controllers():
        if c.id == victim or c.core.rejoining:
            continue
        if needed <= _held_requests(c):
            return True
    return False


def _held_requests(controller: SimController) -> set[int]:
    """The request numbers whose entries ``controller``'s history holds."""
    held: set[int] = set()
    history = controller.history
    for lognr in history.above(0):
        held.update(entry.reqnr for entry in history.get(lognr).entries)
    return held


def cut_master(world: World, length: float) -> None:
    """Partitions the drone's master from the drone for ``length`` seconds."""
    cid = world.drone.seq.master
    world.trace(f"master {cid} cut from the drone for {length:.3f}s")
    world.net.cut(cid, DRONE)
    world.loop.after(length, heal, world, [(cid, DRONE)])


def faults_stop(world: World) -> None:
    """The end of the fault window: the network stops losing and duplicating."""
    world.faulty = False
    world.trace("faults stop")


def drop_link(world: World) -> None:
    """One connection drops: a ring stream or a controller's drone connection."""
    rng, live = world.rng, world.live_controllers()
    if not live:
        return
    controller = rng.choice(live)
    links = [link for _, link in sorted(controller.links.items())]
    if links and rng.random() < 0.6:
        rng.choice(links).break_("dropped")
    else:
        controller.drone_link.break_("dropped")


def partition(world: World, group: list[int], heal_at: float) -> None:
    """Cuts ``group`` from every other node until ``heal_at``."""
    others = [n for n in (*world.ring, DRONE) if n not in group]
    pairs = [(a, b) for a in group for b in others]
    world.trace(f"partition {sorted(group)} | {sorted(others)} until {heal_at:.3f}")
    for a, b in pairs:
        world.net.cut(a, b)
    world.loop.at(heal_at, heal, world, pairs)


def heal(world: World, pairs: list[tuple[int, int]]) -> None:
    """Ends a partition."""
    world.trace(f"partition heals {pairs}")
    for a, b in pairs:
        world.net.heal(a, b)


def killable(world: World, victim: SimController) -> bool:
    """Whether the mix may kill ``victim`` now.

    Never a master in any sense (issue 10, failover, is not built; unless
    ``kill_master``). Then, unless the finding is allowed: one controller
    down at a time, and the victim's predecessor and successor each hold
    every message whose origin is the victim or themselves, as a restart
    needs (F3); no scripted or queued Handover names it (F4). A victim owed
    the acknowledgement of a handover message may be killed (F9 is fixed;
    ``--allow F9`` prefers such victims).
    """
    options = world.options
    if options.kill_master:
        return True
    if victim.master_like:
        return False
    allow = options.allow
    predecessor = world.controller(victim.protocol.predecessor)
    successor = world.controller(victim.protocol.successor)
    if "F3" not in allow:  # F3 is fixed; the keep-out stays (findings.py)
        if any(not c.alive for c in world.controllers.values()):
            return False
        by_origin = world.by_origin
        mine = by_origin.get(victim.id, set())
        for neighbour in (predecessor, successor):
            needed = mine | by_origin.get(neighbour.id, set())
            if any(lognr not in neighbour.history for lognr in needed):
                return False
    if "F4" not in allow:  # F4 is fixed; the keep-out stays (findings.py)
        drone = world.drone
        named = {line.new_master for line in drone.seq.script.values()}
        named |= {item.new_master for item in drone.queue if isinstance(item, HandoverOrder)}
        if victim.id in named:
            return False
    return True


def _handover_unacked_to(world: World, victim: SimController) -> bool:
    for other in world.controllers.values():
        link = other.links.get(victim.id)
        if link is not None and any(m.handover for m in link.unacked.values()):
            return True
    return False


def kill(world: World, restart_at: float, tries: int = 0) -> None:
    """Kills a controller the mix may kill (``killable``); it restarts with nothing later.

    Tried again every 20 ms for up to a second while nobody may be killed.
    """
    candidates = [c for c in world.live_controllers() if killable(world, c)]
    if not candidates:
        if tries < 50:
            world.loop.after(0.02, kill, world, max(restart_at, world.loop.now + 0.04), tries + 1)
        return
    if "F9" in world.options.allow:  # prefer F9's victims: a handover to them not yet acked
        owed = [c for c in candidates if _handover_unacked_to(world, c)]
        candidates = owed or candidates
    victim = world.rng.choice(candidates)
    victim.kill()
    world.loop.at(max(restart_at, world.loop.now + 0.01), world.restart_controller, victim.id)


def drone_crash(world: World, restart_at: float) -> None:
    """The drone service dies and comes back from its durable state."""
    if world.drone.up:
        world.drone.crash()
        world.loop.at(restart_at, world.drone.restart)


def vehicle_outage(world: World, back_at: float) -> None:
    """The vehicle link is out until ``back_at``."""
    world.outages += 1
    world.drone.vehicle.connected = False
    world.loop.at(back_at, vehicle_back, world)


def vehicle_back(world: World) -> None:
    """One outage ends (they may overlap)."""
    world.outages -= 1
    world.drone.vehicle.connected = world.outages == 0


def give_up(world: World, code: grpc.StatusCode) -> None:
    """A mission program gives up on its current call, where that keeps the mission deterministic.

    The master's call, also one whose reply a handover overtook (the
    scenario that checks F5's fix); or a replica's held call whose entry the
    master logged as given up with the same code, the program's last too
    (F8's).
    """
    candidates: list[tuple[int, grpc.StatusCode]] = []
    for c in world.live_controllers():
        if c.answering:
            candidates.append((c.id, code))
        reqnr = c.waiting_call_reqnr()
        if reqnr is not None and reqnr in world.given_up:
            candidates.append((c.id, world.given_up[reqnr]))
    if candidates:
        cid, chosen = world.rng.choice(candidates)
        world.controller(cid).give_up(chosen)


def ready_for_handover(world: World, new_master: int) -> bool:
    """Whether the mix may hand over to ``new_master`` now.

    Unless the finding is allowed: the drone's master is ACTIVE with its
    Connect stream up (so it hands its log over), no other Handover is
    queued and no prepared handover under way (F1); the target is alive,
    not the master, and holds no drone session (its start-up question was
    answered, and it is not catching up as a granted master) (F4); the
    programs have started (F1).
    """
    allow = world.options.allow
    drone = world.drone
    if not drone.up:
        return False
    if "F1" not in allow and not world.programs_started:
        return False
    if "F1" not in allow:
        if any(isinstance(item, HandoverOrder) for item in drone.queue):
            return False
        if drone.seq.preparing is not None:
            # A prepared handover may move the master before this call takes the
            # lock: it would find a new master not ACTIVE yet (F1's ground).
            return False
        master = world.controller(drone.seq.master)
        session = master.session
        if not master.alive or master.protocol.state is not State.ACTIVE:
            return False
        if session is None or not session.connected:
            return False
    if "F4" not in allow:  # F4 is fixed; the keep-out stays (findings.py)
        target = world.controller(new_master)
        if not target.alive or not target.answered or target.session is not None:
            return False
    return new_master != drone.seq.master


def handover(world: World, new_master: int, tries: int = 0) -> None:
    """A Handover call, when the mix allows it (tried again every 50 ms for up to 2 s)."""
    if ready_for_handover(world, new_master):
        world.drone.handover_rpc(new_master, prepared=world.options.prepared)
    elif tries < 40:
        world.loop.after(0.05, handover, world, new_master, tries + 1)


def there_and_back(world: World, new_master: int, delay: float) -> None:
    """Two Handover calls back to back: to ``new_master``, and ``delay`` later back again,
    at once, before the old master may have heard of the first (checks F2's fix)."""
    old = world.drone.seq.master
    handover(world, new_master)
    world.loop.after(delay, world.drone.handover_rpc, old)


def garbled_request(world: World) -> None:
    """An Invoke in the master's name and epoch, its reqnr far beyond any the master will use."""
    seq = world.drone.seq
    if world.drone.up:
        world.drone.receive_invoke(
            Request(seq.master, seq.epoch, 2**63, GET_POSITION, b"", -1, None, -1)
        )
