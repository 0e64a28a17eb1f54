"""Runs the handover policy (``policy.py``) in the drone service, from its own telemetry.

Every ``POLICY_TICK_S`` the runner reads the vehicle's position and velocity
from the mobility backend's telemetry cache, each controller's link from the
drone's streams and pings (``DroneService.link_states``: a controller holding a
standby or Connect stream is up, the drone's last sighting says for how long
one has been down, and ``link_probe.py`` measures its round trip), asks the pure
policy, and carries the decision out:

- ``handover``: ``DroneCore.policy_handover`` decides and the service applies
  its effects: prepared (docs/design.md "Prepared handover": the new master is
  caught up while the vehicle flies on, and the drone moves the master once it
  has), or at once through ``DroneCore.hand_over``, the path of the Handover
  RPC, for a takeover or a master that cannot prepare; under the execution
  lock, so the switch falls between two requests; only if the master is still
  the one the policy decided for.
- ``fly_on``: no controller is usable, but the leg the vehicle flies (the
  master's last Goto) leads into a station's range: nothing is done, the
  vehicle flies on and the mission waits (no master can reach the drone);
  the station is taken over as soon as it is usable. A vehicle holding
  resumes its leg.
- ``hold``: no controller is usable, and the leg leads into no range. The
  vehicle holds position (MAVLink hold/loiter through the backend, if it is
  in the air) and the mission waits. When a controller is usable again (or a
  leg leads to one) the vehicle *resumes*: it flies on to the target of the
  master's last Goto (it was stopped short of it, and the program polls until
  it is there); not while the policy waits for the master's lost link (as a
  restarted drone does for its start-up grace). A request of the master while
  holding ends the hold instead: the master commands again.

The vehicle outlives the drone service: an autopilot told to hold holds until
told otherwise. So the leg and the hold are kept in the drone's state file
(``store.PolicyMemory``, the hold written before the Hold is sent), and a
restarted drone holds again from its start (GetStatus says so), sends Hold
again at its first ``hold`` and resumes the leg at its first other decision.
A Hold or a resume's Goto that fails leaves the vehicle's state unknown: the
runner holds as far as it knows and sends the command again at the next
decision.

Every decision that changes what the drone does is logged with its reason and
kept for GetStatus (``policy_decisions``); the latest one is always shown.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Mapping
from typing import TYPE_CHECKING

from google.protobuf.message import Message

from baton.drone.mobility_api import latest_position
from baton.drone.policy import (
    ENDS_A_LEG,
    HANDOVER,
    Decision,
    Fix,
    PolicyParams,
    PolicyState,
    Station,
    decide,
    distance_m,
    hold_due,
    resume_due,
)
from baton.drone.safety import FLY, HOLD
from baton.drone.store import PolicyMemory
from baton.logs import get_logger
from baton.rpc.errors import StatusError
from baton.rpc.labels import label, parse
from baton.sdk import Position
from baton.sdk import distance_m as geo_distance_m
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2

if TYPE_CHECKING:
    from baton.drone.service import DroneService

# How often the policy looks, wall seconds.
POLICY_TICK_S = 0.1
# Decisions kept for GetStatus.
DECISIONS_KEPT = 100
# An unchanged decision is logged again this often (wall seconds).
DECISION_LOG_PERIOD_S = 5.0
# Closer than this to the last Goto's target, a resume sends nothing.
RESUME_MIN_M = 1.0


class PolicyRunner:
    """The handover policy's I/O: telemetry in, handovers and holds out."""

    def __init__(
        self,
        service: DroneService,
        params: PolicyParams,
        stations: Mapping[int, Station],
        speedup: float,
    ) -> None:
        self.service = service
        self.params = params
        self.stations = dict(stations)
        self.speedup = speedup
        self.state = PolicyState()
        self.latest: drone_pb2.PolicyDecision | None = None
        self.decisions: deque[drone_pb2.PolicyDecision] = deque(maxlen=DECISIONS_KEPT)
        self.holding = False
        self._held_vehicle = False  # the hold stopped a flying vehicle
        # The vehicle may not be doing what the runner believes (a hold kept across a
        # restart, a Hold or a resume's Goto that failed): the next decision sends its
        # command even though the runner holds already.
        self._unsure = False
        self._held_before_restart = False  # for the resume's reason
        self._last_goto: api.GotoRequest | None = None
        # Resumes sent since the mission's start (DroneStatus.policy_resumes), kept.
        self.resumes = 0
        self._fix: Fix | None = None
        # The vehicle's position at the last decision (for the drone's own takeovers).
        self.position: api.Position | None = None
        self._logged_at = 0.0
        self.log = get_logger("drone.policy", policy=params.name)

    # -- what the service tells the runner ---------------------------------------------

    def pin(self, master: int) -> None:
        """The script or the operator made ``master`` master: kept while it is usable."""
        self.state = self.state.pin(master)

    def restore(self) -> None:
        """A restarted drone: the leg and the hold its predecessor kept in the store.

        A command of the master that changes the leg, cut off by the restart, leaves
        both unknown (the vehicle may be acting on it; the master is told UNKNOWN): they
        are forgotten, so that no older leg is flown again.
        """
        service = self.service
        if service.store is None:
            return
        memory = service.store.load_policy()
        self.resumes = memory.resumes
        cut = service.cut_off
        route = None if cut is None else service.dispatcher.routes.get(cut.method)
        if cut is not None and route is not None and route.service == "Mobility":
            if _changes_the_leg(route.name):
                self.log.warning(
                    "a command cut off by the restart: the leg and the hold before it are "
                    "forgotten (the vehicle may have acted on it)",
                    method=route.name,
                    reqnr=cut.reqnr,
                    held=memory.held,
                )
                self._save()
                return
        self._last_goto = None if memory.leg is None else api.GotoRequest.FromString(memory.leg)
        if memory.held:
            self.holding = self._held_vehicle = self._unsure = True
            self._held_before_restart = True
            self.log.warning(
                "the vehicle was held by the policy before the restart: held until a "
                "controller is usable, then flown on to the last Goto's target",
                leg_to=_leg_to(self._last_goto),
            )

    def executed(self, method_name: str, request: Message) -> None:
        """A Mobility command of the master was executed: remember the leg it flies; a
        command while holding ends the hold (the master commands again)."""
        if method_name == "Goto":
            assert isinstance(request, api.GotoRequest)
            self._last_goto = request
        elif method_name in ENDS_A_LEG:
            self._last_goto = None
        else:
            return
        if self.holding:
            self.holding = self._held_vehicle = self._unsure = False
            self.log.info("hold ended by the master's command", method=method_name)
        self._save()

    def in_range(self) -> set[int] | None:
        """The controllers whose range holds the vehicle now; None before the first fix."""
        fix = self._fix
        if fix is None:
            return None
        return {cid for cid, s in self.stations.items() if distance_m(s, fix) <= s.range_m}

    def fill_status(self, status: drone_pb2.DroneStatus) -> None:
        """The policy's part of GetStatus."""
        status.handover_policy = parse(drone_pb2.HandoverPolicy, self.params.name)
        if self.latest is not None:
            status.policy_decision.CopyFrom(self.latest)
        status.policy_decisions.extend(self.decisions)
        status.holding = self.holding and self._held_vehicle  # a flying vehicle stopped
        status.policy_resumes = self.resumes

    # -- the loop --------------------------------------------------------------------------

    async def run(self) -> None:
        """Decides every POLICY_TICK_S until cancelled."""
        self.log.info(
            "handover policy on",
            stations={cid: s.range_m for cid, s in self.stations.items()},
            margin_m=self.params.margin_m,
            dwell_s=self.params.dwell_s,
            lead_s=self.params.lead_s,
        )
        while True:
            try:
                await self.tick()
            except StatusError as err:
                self.log.warning("policy step failed", reason=err.message)
            await asyncio.sleep(POLICY_TICK_S)

    async def tick(self) -> Decision | None:
        """One decision, carried out; None while the vehicle's position is not known."""
        service = self.service
        position = await latest_position(service.vehicle)
        if position.latitude_deg == 0 and position.longitude_deg == 0:
            return None
        north, east = service.vehicle.ground_velocity() or (0.0, 0.0)
        goto = self._last_goto
        leg_to = None if goto is None else Position(goto.latitude_deg, goto.longitude_deg)
        fix = Fix(Position.from_proto(position), north, east, leg_to)
        self._fix, self.position = fix, position
        master = service.seq.master
        links = service.link_states(self.speedup)
        decision, self.state = decide(
            self.params, self.stations, fix, links, master, self.state, self._now()
        )
        self._note(decision, position, master)
        if decision.action == HANDOVER:
            assert decision.target is not None
            async with service.execution_lock:
                _, effects = service.core.policy_handover(
                    decision, master, service.streams.master_connected, time.time(), position
                )
                service.apply(effects)
        elif hold_due(decision, self.holding, self._unsure):
            await self._hold(decision)
        if resume_due(decision, self.holding):
            await self._resume(master)
        return decision

    def _now(self) -> float:
        """Mission seconds (the policy's clock)."""
        return time.time() * self.speedup

    def _note(self, decision: Decision, position: api.Position, master: int) -> None:
        """Keeps the decision for GetStatus and logs it when it changes what the drone does."""
        record = drone_pb2.PolicyDecision(
            action=decision.action,
            target=decision.target if decision.target is not None else -1,
            takeover=decision.takeover,
            reason=decision.reason,
            decided_at=time.time(),
            position=position,
            master=master,
        )
        self.latest = record
        last = self.decisions[-1] if self.decisions else None
        changed = last is None or (last.action, last.target, last.master) != (
            record.action,
            record.target,
            record.master,
        )
        now = time.monotonic()
        if changed:
            self.decisions.append(record)
        if changed or now - self._logged_at >= DECISION_LOG_PERIOD_S:
            self._logged_at = now
            log = self.log.info if changed else self.log.debug
            log(
                "policy decision",
                action=label(drone_pb2.PolicyAction, decision.action),
                target=decision.target,
                takeover=decision.takeover,
                reason=decision.reason,
                latitude_deg=position.latitude_deg,
                longitude_deg=position.longitude_deg,
            )

    def _save(self, held: bool | None = None) -> None:
        """Keeps the leg and the hold (``held``, else what the runner believes) in the
        drone's state file, if it has one."""
        store = self.service.store
        if store is None:
            return
        goto = self._last_goto
        store.save_policy(
            PolicyMemory(
                None if goto is None else goto.SerializeToString(),
                self.holding and self._held_vehicle if held is None else held,
                self.resumes,
            )
        )

    async def _hold(self, decision: Decision) -> None:
        """No controller usable: the vehicle holds position while it flies (again, when
        the runner is not sure it does)."""
        service = self.service
        again = self.holding
        async with service.execution_lock:
            if service.core.failsafe is not None:
                return  # the failsafe's action has the vehicle: a hold must not stop it
            state = await service.vehicle.GetFlightState(api.GetFlightStateRequest())
            if state.in_air:
                # Kept first: a drone restarted once the vehicle holds must know it does
                # (one restarted before it does holds it again).
                self._save(held=True)
                try:
                    service.core.commanding(HOLD, time.time())
                    await service.vehicle.Hold(api.HoldRequest())
                    service.commanded(HOLD)
                except BaseException:
                    # It may hold or not: held as far as the drone knows, sent again next.
                    self.holding = self._held_vehicle = self._unsure = True
                    raise
            self.holding, self._held_vehicle, self._unsure = True, state.in_air, False
            self._save()
        if not self._held_vehicle:
            message = "no controller usable (vehicle on the ground: nothing to hold)"
        elif again:
            message = "no controller usable: holding position again (it may not have held)"
        else:
            message = "no controller usable: holding position"
        self.log.warning(message, reason=decision.reason)

    async def _resume(self, master: int) -> None:
        """A controller is usable again: fly on to the master's last Goto target."""
        service = self.service
        async with service.execution_lock:
            if not self.holding:
                return  # the master's command ended it meanwhile
            if service.core.failsafe is not None:
                # The failsafe's action has the vehicle: no flying on to the leg.
                self.holding = self._held_vehicle = self._unsure = False
                self._save()
                return
            goto, held, restarted = self._last_goto, self._held_vehicle, self._held_before_restart
            here, away = None, 0.0
            if held and goto is not None:
                here = await service.vehicle.GetPosition(api.GetPositionRequest())
                target = Position(goto.latitude_deg, goto.longitude_deg)
                away = geo_distance_m(Position.from_proto(here.position), target)
                if away > RESUME_MIN_M:
                    try:
                        service.core.commanding(FLY, time.time())
                        await service.vehicle.Goto(goto)
                        service.commanded(FLY)
                    except BaseException:
                        # It may fly on or hold still: resumed again at the next decision
                        # (or held again, if that is a hold).
                        self._unsure = True
                        raise
                    self.resumes += 1
            self.holding = self._held_vehicle = self._unsure = False
            self._held_before_restart = False
            self._save()
        if here is None or away <= RESUME_MIN_M:
            if held:
                self.log.info(
                    "a controller is usable again: nothing to resume "
                    + ("(no Goto known)" if goto is None else "(at the last Goto's target)")
                )
            return
        reason = f"a controller is usable again: flying on to the last Goto's target ({away:.0f} m)"
        if restarted:
            reason += ", held before the drone's restart"
        record = drone_pb2.PolicyDecision(
            action=drone_pb2.POLICY_ACTION_RESUME,
            target=-1,
            reason=reason,
            decided_at=time.time(),
            position=here.position,
            master=master,
        )
        self.decisions.append(record)
        self.log.info(
            "policy decision",
            action=label(drone_pb2.PolicyAction, drone_pb2.POLICY_ACTION_RESUME),
            reason=reason,
        )


def _changes_the_leg(method_name: str) -> bool:
    """Whether a Mobility command of the master sets the leg the vehicle flies."""
    return method_name == "Goto" or method_name in ENDS_A_LEG


def _leg_to(goto: api.GotoRequest | None) -> tuple[float, float] | None:
    return None if goto is None else (goto.latitude_deg, goto.longitude_deg)
