"""The simulated drone's handover policy: ``drone/policy_runner.py``'s ``PolicyRunner`` in
virtual time, asking the real, pure ``policy.decide`` (``--policy``).

Every ``POLICY_TICK_S`` of virtual time (mission seconds: the simulation runs
at 1x) ``tick`` builds the vehicle's ``Fix`` from the corridor's ground truth
(``corridor.py``: the simulated autopilot's telemetry), each controller's
``LinkState`` as ``DroneService.link_states`` does (up while it holds a
stream, else down since the drone last saw it), asks ``decide``, and carries
the decision out as ``PolicyRunner.tick`` does, under the drone's execution
lock (a ``PolicyStep`` queued behind the requests, taken by
``SimDrone.policy_handover``): ``DroneCore.policy_handover``, a handover
prepared if the master can prepare, else at once (a takeover when the
decision says so), only if the master is still the one decided for;
``hold`` stops the vehicle, and the first decision that is not ``hold``
resumes it. As in the runner, the next tick waits for the step.

Not mirrored: the link's round trip (``link_probe.py``: the simulated links
are never slow enough to matter, so ``rtt_s`` stays unknown and a link that
is up is healthy), the decisions' log and GetStatus, and the resume's Goto
(the vehicle flies on; it is not counted as a command: the testbed's report
takes the drone's resumes off the same way).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from baton.drone.policy import (
    ENDS_A_LEG,
    HANDOVER,
    Decision,
    LinkState,
    PolicyState,
    decide,
    distance_m,
    hold_due,
    resume_due,
)
from baton.drone.policy_runner import POLICY_TICK_S, _changes_the_leg
from baton.rpc.labels import label
from baton.rpc.methods import drone_api
from baton.v1 import drone_pb2

if TYPE_CHECKING:
    from baton.drone.store import Intent
    from baton.sim.corridor import Corridor
    from baton.sim.drone import SimDrone


@dataclass(frozen=True)
class PolicyStep:
    """A decision that acts, waiting for the drone's execution lock (``PolicyRunner.tick``)."""

    decision: Decision
    master: int  # the master it was decided for


class SimPolicyRunner:
    """One drone service's policy runner (a restarted drone has a new one)."""

    def __init__(self, drone: SimDrone, corridor: Corridor) -> None:
        self.drone = drone
        self.corridor = corridor
        self.state = PolicyState()
        self.holding = False
        self._held_vehicle = False
        self._in_range: set[int] | None = None  # at the last decision (PolicyRunner.in_range)
        self._ticking = False
        self._last_action = -1  # for the trace: a decision is traced when it changes

    # -- what the service tells the runner (PolicyRunner's) ----------------------------

    def pin(self, master: int) -> None:
        """The script or the operator made ``master`` master: kept while it is usable."""
        self.state = self.state.pin(master)

    @property
    def held_vehicle(self) -> bool:
        """Whether the policy holds the vehicle (what the store keeps: PolicyMemory.held)."""
        return self.holding and self._held_vehicle

    def restore(self, held: bool, cut_off: Intent | None) -> None:
        """PolicyRunner.restore: a restarted drone holds again if its predecessor held
        (resumed at its first decision that is not ``hold``), unless a command that
        changes the leg was cut off by the restart (forgotten; the leg is the corridor's)."""
        if cut_off is not None:
            route = drone_api().get(cut_off.method)
            if route is not None and route.service == "Mobility" and _changes_the_leg(route.name):
                return
        self.holding = self._held_vehicle = held

    def executed(self, method_name: str) -> None:
        """PolicyRunner.executed: a Goto, or a command that ends a leg, ends a hold (the
        vehicle leaves hold mode on it: ``Corridor.fly_on``)."""
        if method_name == "Goto" or method_name in ENDS_A_LEG:
            self.corridor.fly_on()
            if self.holding:
                self.holding = self._held_vehicle = False
                self.drone.world.trace("policy: hold ended by the master's command")

    def in_range(self) -> set[int] | None:
        """The controllers whose range held the vehicle at the last decision; None before."""
        return self._in_range

    # -- the loop -----------------------------------------------------------------------

    def start(self) -> None:
        """Ticks every POLICY_TICK_S if it is not already (``PolicyRunner.run``; the loop
        stops, to let a run end, once no program has anything left to do and no
        preparation is under way, and ``SimDrone.watch`` starts it again)."""
        if not self._ticking:
            self._ticking = True
            self.drone.world.loop.after(POLICY_TICK_S, self._tick)

    def _tick(self) -> None:
        drone, world = self.drone, self.drone.world
        self._ticking = False
        if drone.policy is not self or not drone.up:
            return  # the service died; a restarted one has its own runner
        if not (
            world.mission_open() or drone.seq.preparing is not None or self.corridor.left_behind()
        ):
            return
        step = self.decide()
        if step is None:
            self.start()
        else:
            drone.queue_policy_step(step)  # the step starts the next tick when done

    def decide(self) -> PolicyStep | None:
        """PolicyRunner.tick up to the lock: the decision, and the step that carries it
        out if it acts (None if it does not)."""
        drone, corridor = self.drone, self.corridor
        fix = corridor.fix()
        stations = corridor.stations
        self._in_range = {cid for cid, s in stations.items() if distance_m(s, fix) <= s.range_m}
        master = drone.seq.master
        now = drone.world.loop.now
        decision, self.state = decide(
            corridor.params, stations, fix, self.link_states(now), master, self.state, now
        )
        action = label(drone_pb2.PolicyAction, decision.action)
        if decision.action == HANDOVER:
            drone.world.trace(
                f"policy: {action} {master} -> {decision.target}"
                f"{' (takeover)' if decision.takeover else ''}: {decision.reason}"
            )
        elif decision.action != self._last_action:
            drone.world.trace(f"policy: {action}: {decision.reason}")
        self._last_action = decision.action
        if (
            decision.action == HANDOVER
            or hold_due(decision, self.holding)
            or resume_due(decision, self.holding)
        ):
            return PolicyStep(decision, master)
        return None

    def link_states(self, now: float) -> dict[int, LinkState]:
        """DroneService.link_states (at 1x): up while it holds a stream, else down since
        last seen (or since the end of the start-up grace); no round trip measured."""
        drone = self.drone
        up = drone.reachable()
        links = {}
        for cid in drone.seq.ring:
            down = 0.0 if cid in up else (drone.core.down_for(cid, now) or 0.0)
            links[cid] = LinkState(up=cid in up, down_for_s=down)
        return links

    def carry_out(self, step: PolicyStep) -> None:
        """PolicyRunner.tick after its decision, under the lock: the handover, the hold,
        the resume; then the next tick."""
        drone, decision = self.drone, step.decision
        if decision.action == HANDOVER:
            assert decision.target is not None
            drone.policy_decided[drone.policy_handover(step.master, decision)] += 1
        elif hold_due(decision, self.holding):
            # PolicyRunner._hold: the vehicle is in the air all along the corridor.
            self.corridor.hold()
            self.holding = self._held_vehicle = True
            drone.policy_decided["hold"] += 1
            drone.world.trace(f"policy: the vehicle holds ({decision.reason})")
        if resume_due(decision, self.holding):
            # PolicyRunner._resume: fly on to the last Goto's target (the corridor's end).
            held, self.holding, self._held_vehicle = self._held_vehicle, False, False
            if held:
                self.corridor.fly_on()
                drone.policy_decided["resume"] += 1
                drone.world.trace("policy: the vehicle flies on (a controller is usable again)")
        self.start()
