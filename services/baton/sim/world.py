"""One seed's world: a ring of controllers, the drone, the network, the faults, the oracles.

``run_seed(seed)`` builds everything from ``random.Random(seed)``: 2 to 8
controllers in a random ring order (the first is the drone's initial
master: the ring is a cycle, so this loses nothing), a flush limit of 0
to 4 KB, the drone's reply cache window, a handover script, a mission
program and the faults; runs it in virtual time until nothing is left to
do or the liveness bound passes; and checks the oracles. The same seed
and options always take the same events in the same order (``Outcome.digest``).
"""

from __future__ import annotations

import hashlib
import itertools
import random
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import grpc

from baton.controller.core import ControllerCore, CoreEffect
from baton.controller.protocol import SendLog, State
from baton.drone.dedupe import DEFAULT_WINDOW
from baton.drone.safety import ACTIONS, SafetyParams
from baton.drone.sequencer import ScriptedHandover
from baton.sim.controller import SimController
from baton.sim.corridor import Corridor
from baton.sim.drone import SimDrone
from baton.sim.faults import FaultPlan, handover, plan_faults, stall_ring, survivable
from baton.sim.findings import FINDINGS
from baton.sim.invariants import Invariants
from baton.sim.loop import Loop
from baton.sim.lying import Lie, SimKeys, sim_keys
from baton.sim.mission import MissionCall, random_mission
from baton.sim.mutations import mutated
from baton.sim.network import DRONE, Network
from baton.sim.oracles import Violation, check
from baton.v1 import drone_pb2
from baton.v1.drone_pb2 import HandoverRecord
from baton.v1.ring_pb2 import LogMessage

if TYPE_CHECKING:
    from baton.sim.explore import Scope

# Beyond the fault window, how long the mission may take to finish, at most.
QUIET_BOUND_S = 60.0
QUIET_BOUND_PER_CALL_S = 2.0
MAX_EVENTS = 2_000_000
# The default mix's share of prepared script lines (with --lose-master: none, unless
# --prepared makes them all prepared), and the drone's prepare timeouts drawn.
PREPARED_SHARE = 0.25
PREPARE_TIMEOUTS_S = (0.3, 1.0, 3.0, 10.0)
# The range the autopilot's GCS failsafe time is drawn from (--autopilot), mission
# seconds: about the drone restarts' dead times (faults.plan_faults), so that some outlast it.
GCS_TIMEOUTS_S = (0.2, 1.0)


@dataclass(frozen=True)
class SimOptions:
    """What a run may vary besides the seed (each is a flag of ``python -m baton.sim``)."""

    min_calls: int = 8
    max_calls: int = 32
    # Kills (restarted later) may hit a master in any sense.
    kill_master: bool = False
    # Issue 10's scenario: the master lost for good (killed, never restarted) at
    # any point, or its drone link cut for a while (faults.plan_failover).
    lose_master: bool = False
    # The drone's takeover time and the ring's detection time, seconds (None: 3 in
    # the default mix, drawn from 1, 1.5 and 3 with lose_master; 0 turns them off).
    takeover_after: float | None = None
    # Every scripted handover and every Handover call of the faults is prepared
    # (docs/design.md, "Prepared handover"); without it a quarter of the default mix's
    # script lines are (World: PREPARED_SHARE), and no Handover call.
    prepared: bool = False
    # A handover policy (drone/policy.py's "nearest" or "predictive"): the vehicle flies
    # a corridor of stations with radio range, and the drone's policy moves the master
    # by prepared handovers (corridor.py, policy_runner.py); None: no policy.
    policy: str | None = None
    # The ring cut from a new master right after a cooperative switch, for a drawn time
    # around how long the drone lets a master go without serving (its drone link stays
    # up): the handover message cannot reach it, so it never connects
    # (faults.plan_stall).
    stall_new_master: bool = False
    # Issue 32's lost-link failsafe on, and every station cut from the drone at a drawn
    # moment (faults.plan_failsafe).
    failsafe: bool = False
    # Issue 32's operator commands at drawn moments: pause then resume, pause then
    # abort, abort, land-now (faults.plan_operator).
    operator: bool = False
    # Issue 33's lying station: every part holds keys and checks them, and one station
    # forges frames at drawn moments (lying.py).
    lying: bool = False
    # Issue 32's autopilot taking the vehicle over at a drawn moment: a return, a
    # landing or a pilot's mode the drone did not command (faults.plan_autopilot).
    autopilot: bool = False
    # Known findings (findings.py) whose scenarios this run lets in.
    allow: frozenset[str] = frozenset()
    mutation: str | None = None
    trace: bool = False
    # The invariants (invariants.py) after every this many events (1: every event;
    # 0: not checked).
    check_every: int = 1

    def flags(self) -> str:
        """The command-line flags that give these options (defaults left out)."""
        default = SimOptions()
        parts = []
        if (self.min_calls, self.max_calls) != (default.min_calls, default.max_calls):
            parts.append(f"--calls {self.min_calls}-{self.max_calls}")
        if self.kill_master:
            parts.append("--kill-master")
        if self.lose_master:
            parts.append("--lose-master")
        if self.prepared:
            parts.append("--prepared")
        if self.policy is not None:
            parts.append(f"--policy {self.policy}")
        if self.stall_new_master:
            parts.append("--stall-new-master")
        if self.failsafe:
            parts.append("--failsafe")
        if self.operator:
            parts.append("--operator")
        if self.lying:
            parts.append("--lying")
        if self.autopilot:
            parts.append("--autopilot")
        if self.takeover_after is not None:
            parts.append(f"--takeover-after {self.takeover_after:g}")
        if self.allow:
            parts.append(f"--allow {','.join(sorted(self.allow))}")
        if self.mutation:
            parts.append(f"--mutation {self.mutation}")
        if self.check_every != default.check_every:
            parts.append(f"--check-every {self.check_every}")
        return " ".join(parts)


@dataclass
class Outcome:
    """What one seed did and what the oracles found."""

    seed: int
    options: SimOptions
    summary: str
    faults: str
    violations: list[Violation]
    events: int
    virtual_s: float
    digest: str
    known: list[str] = field(default_factory=list)
    # Peaks over the run: log queue, unacknowledged messages on one stream, reply cache.
    peaks: dict[str, int] = field(default_factory=dict)
    trace: list[str] = field(default_factory=list)
    # Prepared handovers: begun, carried out as prepared, forced at the timeout.
    prepared: dict[str, int] = field(default_factory=dict)
    # With a policy: what its steps did ("prepare", "at once", "takeover", "hold"...)
    # and how its handovers ended ("prepared on the word", "forced at the timeout"...).
    policy_decided: dict[str, int] = field(default_factory=dict)
    policy_switches: dict[str, int] = field(default_factory=dict)
    # Controllers still ACTIVE as master at the end that the drone's master is not
    # (with a policy: taken over out of range, never back in it; docs/design.md).
    left_behind: list[int] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """No oracle fired."""
        return not self.violations

    @property
    def failed(self) -> bool:
        """An oracle fired, and no known finding (findings.py) struck to explain it."""
        return bool(self.violations) and not self.known

    @property
    def replay(self) -> str:
        """The one-line command that replays this seed exactly."""
        flags = self.options.flags()
        return f".venv/bin/python -m baton.sim --seed {self.seed}" + (f" {flags}" if flags else "")

    def report(self) -> str:
        """The seed, its world, the oracles that fired and the replay command."""
        lines = [f"seed {self.seed}: {self.summary}", f"  faults: {self.faults}"]
        lines += [f"  {v}" for v in self.violations]
        lines += [f"  known finding {k}: {FINDINGS[k].title}" for k in self.known]
        lines.append(f"  replay: {self.replay}")
        return "\n".join(lines)


class World:
    """Everything one seed simulates."""

    def __init__(self, seed: int, options: SimOptions, scope: Scope | None = None) -> None:
        self.seed = seed
        self.options = options
        self.rng = rng = random.Random(seed)
        self.loop = Loop()
        # The invariants, checked after every event (options.check_every).
        self.invariants: Invariants | None = None
        if options.check_every:
            self.invariants = Invariants(self, options.check_every)
            self.loop.after_event = self.invariants.after_event
        self._trace: list[str] | None = [] if options.trace else None
        self._ids = itertools.count(1)
        n = rng.randint(2, 8)
        self.ring = list(range(n))
        rng.shuffle(self.ring)
        self.flush_limit = rng.choice((0, 0, 64, 256, 1024, 2048, 4096))
        # The ring's forwarding (RingConfig.forwarding): cut-through's straight copies
        # to a handover's target on even seeds (frames relayed as they come change only
        # timing, docs/design.md "The ring's forwarding"), the paper's store-and-forward
        # on odd ones; from the seed, so that the random draws stay the same.
        self.cut_through = seed % 2 == 0
        self.program: tuple[MissionCall, ...] = random_mission(
            rng, rng.randint(options.min_calls, options.max_calls)
        )
        cache_window = rng.choice((1, 2, 4, DEFAULT_WINDOW))
        # Which script lines are prepared, and the drone's prepare timeout: from a
        # stream of their own, so that every other draw of the seed stays where it
        # was (a seed without a prepared line runs as before prepared handovers).
        prng = random.Random(f"prepared {seed}")
        self.prepare_timeout = prng.choice(PREPARE_TIMEOUTS_S)
        share = 1.0 if options.prepared else 0.0 if options.lose_master else PREPARED_SHARE
        script: dict[int, ScriptedHandover] = {}
        for line in range(rng.choice((0, 0, 1, 2, 4))):
            reqnr = rng.randint(1, len(self.program))
            prepared = prng.random() < share
            script.setdefault(
                reqnr, ScriptedHandover(reqnr, rng.choice(self.ring), line + 1, prepared)
            )
        if scope is not None:  # explore.py: a small world of its own, not the seed's
            script, cache_window = scope.shape(self)
        self.faulty = True
        # Takeover and ring detection time (config.detection_time_s: takeover_after
        # mission seconds, at least 1 s), from a stream of its own so that the
        # failover draws leave every other draw of the seed where it was.
        self.frng = random.Random(f"failover {seed}")
        # The testbed's 3 s in the default mix (kills, partitions and drone
        # restarts make takeovers and route-arounds there); --lose-master draws
        # 1 to 3 s. Shorter times in the default mix still fail about 1 % of
        # seeds (``--takeover-after 1``: same replies, liveness), not yet here.
        drawn = self.frng.choice((1.0, 1.5, 3.0)) if options.lose_master else 3.0
        if options.takeover_after is not None:
            drawn = options.takeover_after
        self.takeover_after = self.detection_s = drawn
        # The drone's lost-link failsafe (--failsafe): after a few takeover times with no
        # usable controller, drawn from a stream of its own, as are its action.
        srng = random.Random(f"failsafe {seed}")
        self.safety = SafetyParams()
        # The battery's drain, percent per second (0: it never runs low).
        self.battery_drain = 0.0
        if options.failsafe:
            lost_link = max(drawn, 1.0) * srng.choice((2.0, 3.0, 5.0))
            action = srng.choice(ACTIONS)
            # In half the seeds the battery reaches the 20 % reserve 2 to 30 s in.
            if srng.random() < 0.5:
                self.battery_drain = 80.0 / srng.uniform(2.0, 30.0)
            battery_action = srng.choice(ACTIONS[1:])
            self.safety = SafetyParams(
                lost_link, action, battery_reserve_pct=20.0, battery_action=battery_action
            )
        # The autopilot's own GCS failsafe (--autopilot): the vehicle returns and lands
        # when the drone service is dead this long (0: never), from a stream of its own.
        self.gcs_rng = random.Random(f"gcs {seed}")
        self.autopilot_gcs_timeout = 0.0
        if options.autopilot:
            self.autopilot_gcs_timeout = self.gcs_rng.uniform(*GCS_TIMEOUTS_S)
        # Controllers killed for good (the lose-master fault), and what it did.
        self.lost: set[int] = set()
        self.failover: dict[str, object] = {}
        # Every part's key (--lying), from the seed; None: no keys, nothing checked.
        self.keys: SimKeys | None = sim_keys(seed, self.ring) if options.lying else None
        self.lies: list[Lie] = []  # the lying station's frames (lying.py)
        self.net = Network(self, [*self.ring, DRONE])
        # The corridor and its radio (--policy), from a random stream of its own.
        self.corridor = Corridor(self, options.policy) if options.policy else None
        self.drone = SimDrone(
            self,
            self.ring,
            self.ring[0],
            script,
            cache_window,
            rng.choice((0.0, 0.0, 0.05)),
            self.prepare_timeout,
        )
        self.outages = 0
        # Request numbers the master logged as given up, and with which code.
        self.given_up: dict[int, grpc.StatusCode] = {}
        # Every log number sent, by the message's origin.
        self.by_origin: dict[int, set[int]] = {}
        # The epochs each log number was sent in: more than one, a takeover replaced
        # a framing (the same-replies oracle's ``_would_have_rejoined``).
        self.framings: dict[int, set[int]] = {}
        # Known findings that struck in this run (KNOWN_FINDINGS).
        self.known: set[str] = set()
        self.regressions: list[Violation] = []  # fixed findings that struck again
        self.controllers: dict[int, SimController] = {}
        self.incarnations: list[SimController] = []
        for cid in sorted(self.ring):
            self._new_controller(cid)
        self.plan: FaultPlan = plan_faults(self) if scope is None else scope.quiet(self)
        self.deadline = (
            self.plan.fault_end + QUIET_BOUND_S + QUIET_BOUND_PER_CALL_S * len(self.program)
        )
        self._end_handover_done = False
        self.programs_started = False
        self.summary = (
            f"{n} controllers, ring {self.ring} (initial master {self.ring[0]}), flush limit "
            f"{self.flush_limit} B, {'cut-through' if self.cut_through else 'store-and-forward'}, "
            f"{len(self.program)} calls, cache window {cache_window}, "
            f"script {_script(script, self.prepare_timeout)}, "
            f"loss {self.net.p_loss}, dup {self.net.p_dup}, takeover after {self.takeover_after}s"
        )
        if self.corridor is not None:
            self.summary += f", {self.corridor.describe()}"

    # -- parts ------------------------------------------------------------------------

    def _new_controller(self, cid: int) -> SimController:
        incarnation = sum(1 for c in self.incarnations if c.id == cid)
        controller = SimController(self, cid, incarnation)
        self.controllers[cid] = controller
        self.incarnations.append(controller)
        return controller

    def controller(self, cid: int) -> SimController:
        """The current incarnation of controller ``cid``."""
        return self.controllers[cid]

    def live_controllers(self) -> list[SimController]:
        """Controllers that are running now, by id."""
        return [c for _, c in sorted(self.controllers.items()) if c.alive]

    def restart_controller(self, cid: int, fresh: ControllerCore | None = None) -> None:
        """Restarts controller ``cid`` with nothing: a fresh protocol, history and program.

        A rejoin's protocol is the earlier self's ``fresh_self``."""
        if not self.controllers[cid].alive and cid not in self.lost:
            self.trace(f"controller {cid} restarts")
            controller = self._new_controller(cid)
            if fresh is not None:
                controller.core = fresh
            controller.start()
            self.drone.standby_opened(cid)  # its standby stream: a TakeOver owed to it
            if self.programs_started:
                controller.begin_program()
            self.drone.watch()

    def rejoin(self, controller: SimController) -> None:
        """ControllerApp.rejoin after a takeover fenced ``controller`` or it diverged: its
        program stops, ``ControllerNode.reset`` (new protocol, history cleared, its
        streams stopped), incoming streams dropped so that the predecessors connect
        again and say it all from hello 0, the program restarted from its first call.
        The same as a kill and an immediate restart with nothing."""
        if self.controllers.get(controller.id) is not controller or not controller.alive:
            return
        controller.ended_by = "rejoin"
        # ControllerNode.reset: what the fresh self is given (``ControllerCore.kept_on_rejoin``).
        upto = controller.protocol.kept_history()
        fresh_core = controller.core.fresh_self()
        kept = controller.core.kept_on_rejoin(controller.history)
        controller.kill(
            "rejoins as a replica with nothing"
            if not upto
            else f"rejoins as a replica with log messages 1-{upto}"
        )
        self.restart_controller(controller.id, fresh_core)
        fresh = self.controllers[controller.id]
        for message in kept:
            fresh.on_log(message)

    def drop_streams_to(self, controller: SimController) -> None:
        """RingReceiver.drop_streams: every ring stream into ``controller`` ends, and its
        sender connects again (after its back-off) and hears the hello."""
        for sender in self.live_controllers():
            link = sender.links.get(controller.id)
            if link is not None:
                link.break_(f"dropped by {controller.id}")

    def lose(self, cid: int, why: str, tries: int = 0) -> None:
        """Kills controller ``cid`` for good (the lose-master fault), once that leaves a
        live copy of the log (``faults.survivable``; tried every 50 ms for up to 5 s)."""
        controller = self.controllers[cid]
        if not controller.alive or self.lost:
            return
        if not survivable(self, cid):
            if tries < 100:
                self.loop.after(0.05, self.lose, cid, why, tries + 1)
            return
        self.lost.add(cid)
        controller.ended_by = "lost"
        self.failover["lost"] = f"{cid} at {self.loop.now:.3f}s ({why})"
        controller.kill(f"killed for good ({why})")

    def mission_open(self) -> bool:
        """Whether some program still has calls to make (or has not started), or a call it
        gave up on to settle (node.py _settle_after_the_end waits for the log, or for
        the role: the drone's watch_master, which never stops, may have to grant it,
        and the run goes on until it does)."""
        return not self.programs_started or any(
            not c.done or c.core.abandoned
            for cid, c in self.controllers.items()
            if cid not in self.lost
        )

    def switched(self, record: HandoverRecord) -> None:
        """The drone switched masters: the lose-master or the stall fault may strike now."""
        stall = self.failover.get("stall on switch")
        if isinstance(stall, float) and record.kind == drone_pb2.HANDOVER_KIND_COOPERATIVE:
            del self.failover["stall on switch"]
            stall_ring(self, record.new_master, stall)
        strike = self.failover.pop("on switch", None)
        if (
            strike is not None and record.kind != drone_pb2.HANDOVER_KIND_TAKEOVER
        ):  # a prepared one too
            victim = record.old_master if strike == "old" else record.new_master
            if not survivable(self, victim):  # no live copy of the log would be left
                self.failover["on switch"] = strike  # the next switch
                return
            delay = self.frng.choice((0.0, self.frng.uniform(0.0, 0.02)))
            self.loop.after(delay, self.lose, victim, f"{strike} master right after a handover")

    def after_apply(self, controller: SimController, effects: Sequence[CoreEffect]) -> None:
        """A controller carried out effects: the lose-master fault may strike mid-flush."""
        if self.invariants is not None:
            self.invariants.sent(controller, effects)
        if "on flush" not in self.failover or controller.id != self.drone.seq.master:
            return
        if any(isinstance(e, SendLog) and e.message.origin == controller.id for e in effects):
            if not survivable(self, controller.id):  # no live copy of the log would be left
                return  # the next flush
            del self.failover["on flush"]
            delay = self.frng.choice((0.0, self.frng.uniform(0.0, 0.01)))
            self.loop.after(delay, self.lose, controller.id, "master mid-flush")

    def check_start(self) -> None:
        """Starts the programs once the ring is connected and every controller asked the drone.

        As the testbed starts a mission once every part is ready. Allowing
        F4 drops the second condition.
        """
        if self.programs_started:
            return
        allow, controllers = self.options.allow, self.controllers.values()
        self.drone.watch()
        ring_up = all(c.alive and c.peer(c.protocol.successor).up for c in controllers)
        # With radio range, a controller out of range asks once the vehicle is near.
        covered = self.corridor.covered if self.corridor is not None else set(self.ring)
        asked = all(c.answered or c.id not in covered for c in controllers)
        if ring_up and ("F4" in allow or asked):
            self._start_programs()

    def _start_programs(self) -> None:
        self.programs_started = True
        self.trace("mission programs start")
        for controller in self.live_controllers():
            controller.begin_program()

    def next_id(self) -> int:
        """A fresh number for sessions and calls."""
        return next(self._ids)

    def trace(self, text: str) -> None:
        """Notes an event when tracing (``--trace``)."""
        if self._trace is not None:
            self._trace.append(f"{self.loop.now:10.4f}  {text}")

    def check_overtaken_handover(self, controller: SimController, message: LogMessage) -> None:
        """Fails the run if fixed finding F7 strikes again (findings.py).

        The message names ``controller`` as its origin but is not a handover
        message and was not created by it: a history copy of the handover
        message its old master still has unacknowledged on the direct link.
        Taken as a normal message, it makes the direct one a duplicate, and
        ``controller`` never takes over. A handover whose mastership the drone
        has already ended (a later epoch there) gives no role to lose: one who
        took it would be fenced at its Connect.
        """
        p = controller.protocol
        if (
            message.origin != controller.id
            or message.handover
            or message.sender == controller.id
            or message.lognr in p._received
        ):
            return
        sender = self.controllers.get(message.sender)
        direct = sender.links.get(controller.id) if sender is not None and sender.alive else None
        kept = direct.unacked.get(message.lognr) if direct is not None else None
        if kept is None or not kept.handover:  # settled ones give no role
            return
        if self.drone.seq.epoch <= kept.epoch:
            what = (
                f"F7: controller {controller.id} gets a copy of handover message "
                f"{message.lognr} before the message itself"
            )
            self.regressions.append(Violation("handover-overtaken", what))
            self.trace(what)

    def program_done(self, controller: SimController) -> None:
        """A program finished; the first time, maybe a Handover at the end of the mission."""
        if self.plan.end_handover and not self._end_handover_done:
            self._end_handover_done = True
            others = [cid for cid in self.ring if cid != self.drone.seq.master]
            handover(self, self.rng.choice(others))

    # -- running ----------------------------------------------------------------------

    def run(self) -> Outcome:
        """Runs to the end, checks the oracles, frees the history files."""
        self.begin()
        try:
            self.loop.run(self.deadline, MAX_EVENTS)
            violations = self.verdict()
            if self.loop.events >= MAX_EVENTS:
                violations.append(Violation("liveness", f"more than {MAX_EVENTS} events"))
        finally:
            self.close()
        return Outcome(
            seed=self.seed,
            options=self.options,
            summary=self.summary,
            faults=self.plan.describe(),
            violations=violations,
            events=self.loop.events,
            virtual_s=self.loop.now,
            digest=self._digest(),
            known=sorted(self.known),
            peaks={
                "log queue": max(c.peak_log_queue for c in self.incarnations),
                "unacknowledged": max(
                    (link.peak_unacked for c in self.incarnations for link in c.links.values()),
                    default=0,
                ),
                "reply cache": self.drone.stats.peak_cache,
                "retained replies": self.drone.stats.peak_retained,
            },
            trace=self._trace or [],
            prepared=self._prepared(),
            policy_decided=dict(self.drone.policy_decided),
            policy_switches=dict(self.drone.policy_switches),
            left_behind=[
                c.id
                for c in self.live_controllers()
                if c.id != self.drone.seq.master and c.protocol.state is State.ACTIVE
            ],
        )

    def begin(self) -> None:
        """Starts the corridor, the controllers and, once ready, the programs."""
        if self.corridor is not None:
            self.corridor.start()
        for controller in list(self.controllers.values()):
            controller.start()
        self.check_start()

    def verdict(self) -> list[Violation]:
        """The oracles, the fixed findings that struck again, and the invariants broken."""
        violations = check(self) + self.regressions
        if self.invariants is not None:
            violations += self.invariants.violations
        return violations

    def close(self) -> None:
        """Frees the history files."""
        for controller in self.incarnations:
            controller.close()

    def _prepared(self) -> dict[str, int]:
        drone = self.drone
        records = drone.prepared_records
        timed_out = sum(1 for r in records if r.prepare_timed_out)
        return {
            "begun": drone.preparations,
            "prepared": len(records) - timed_out,
            "forced": timed_out,
            "on the word": drone.words_moved,
            "understated": len(drone.understated),
        }

    def _digest(self) -> str:
        """A fingerprint of what happened: what every program saw and what the vehicle did."""
        h = hashlib.sha256()
        for controller in self.incarnations:
            h.update(repr((controller.id, controller.view, controller.done_at)).encode())
        drone = self.drone
        h.update(repr([(a.time, a.tag) for a in drone.vehicle.commands]).encode())
        h.update(repr([(a.time, a.tag) for a in drone.camera.pictures]).encode())
        h.update(repr((self.loop.events, self.loop.now)).encode())
        return h.hexdigest()[:16]


def _script(script: dict[int, ScriptedHandover], timeout: float) -> str:
    """The script for the summary: (after reqnr, new master), prepared lines marked."""
    lines = sorted(script.values(), key=lambda s: s.after_reqnr)
    text = str([(s.after_reqnr, s.new_master) for s in lines])
    if any(s.prepared for s in lines):
        marked = [f"{s.after_reqnr}->{s.new_master}" for s in lines if s.prepared]
        text += f" (prepared: {', '.join(marked)}; timeout {timeout:g}s)"
    return text


def run_seed(seed: int, options: SimOptions | None = None) -> Outcome:
    """Builds and runs the world of ``seed`` (the caller applies ``options.mutation``)."""
    return World(seed, options or SimOptions()).run()


def run_seeds(seeds: range, options: SimOptions | None = None) -> list[Outcome]:
    """Runs ``seeds`` with ``options.mutation`` applied: a worker process's share of a run.

    Returns the outcomes that failed or that a known finding struck.
    """
    options = options or SimOptions()
    with mutated(options.mutation):
        outcomes = (run_seed(seed, options) for seed in seeds)
        return [o for o in outcomes if o.failed or o.known]
