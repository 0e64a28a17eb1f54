"""The drone's decisions beyond the ``Sequencer``: who is alive, who may take over,
what a request may carry, which failures are booked, what a restart resumes.

Pure like the ``Sequencer`` it holds: no asyncio, no gRPC calls, no clock of
its own (every time is an argument). The drone service (``service.py``) and
the simulation's drone (``baton.sim.drone``) are both drivers of this one
object: they turn streams, requests, timers and the store into calls here and
carry out what comes back, so the simulation checks the code that ships.

The rules it keeps (docs/design.md, "Takeover" and "Exactly once"):

- A controller is *seen* while it holds a stream (standby or Connect) and
  when it sends a request; one never seen since the drone started counts as
  seen at the end of the start-up grace, and the master of a mission resumed
  after a restart at the end of the restart grace.
- The master is lost when it has not been seen for the takeover time; the
  first controller after it in ring order that holds a stream (and, with a
  handover policy, is in range) takes over (``Sequencer.takeover_due``).
- A master *serves* while it holds its Connect stream and when it sends a
  request. One that has not served for ``serve_within_s`` (the longer of
  the takeover time and the prepare timeout: a new master may take as long
  to catch up and connect as a prepared handover's target may) is lost
  whatever streams it holds.
- A request's ``master_answers`` hold only what a controller answers itself
  (Clock replies) or a call its program gave up on: anything else is refused
  INVALID_ARGUMENT before the request is admitted.
- A failure after admission is the request's outcome and is booked, except
  UNAVAILABLE, which means nothing reached the vehicle: the number stays
  unused and the same request may be sent again.
- A call that needs the vehicle (a Mobility or Gimbal call, a picture: ``needs_vehicle``)
  is UNAVAILABLE while the vehicle is not connected, and after a restart with
  the vehicle in the air until the first look at it (``unreachable``): a
  picture is never taken where the vehicle's place is unknown, nor on a way
  home its autopilot chose while the drone service was down.
- The safety net (``safety.py``, docs/operating.md "The safety net"): with no
  usable controller (no request, no stream from one the drone could make
  master) for ``lost_link_s`` while the vehicle is in the air, or with the
  battery below the mission's reserve, the vehicle is put in failsafe. While
  it is, every admitted request is refused before execution
  (FAILED_PRECONDITION, booked: the master logs it as the call's outcome, so
  every replica's program sees the same), until an operator
  resumes. A call beyond a bound of the vehicle (speed, altitude) is refused
  INVALID_ARGUMENT the same way, and one that would move the vehicle out of the
  mission's fence (``fence.py``) OUT_OF_RANGE; the vehicle found out of the fence
  is put in the fence's failsafe, once each time it leaves. A flight mode the
  drone did not command (or a landing, a disarm) while it flies the mission is
  the autopilot taking the vehicle over (``safety.autopilot_takeover``): the
  ``autopilot`` failsafe, in which the drone commands nothing.
- An operator's commands (``operator.py``, docs/operating.md "Operator commands"):
  while paused, the master's next request waits at the drone before admission
  (``holds``); once an abort or a land-now ended the mission, every admitted
  request is refused before execution and booked, as in failsafe.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import grpc

from baton.drone.dedupe import RETAINED_BATCH_BYTES, CachedReply, retained_batches
from baton.drone.effects import (
    Abandon,
    Book,
    DroneEffect,
    Note,
    Preparing,
    SaveCounters,
    Switched,
    TellTakeOver,
    take_over_event,
)
from baton.drone.fence import move_refusal
from baton.drone.invariants import DroneWatch, InvariantBroken
from baton.drone.operator import Operator, OperatorCommand
from baton.drone.policy import PREPARE, SWITCH, Decision, handover_step
from baton.drone.safety import (
    VEHICLE_ACTIONS,
    Bound,
    Failsafe,
    ModeSeen,
    SafetyParams,
    VehicleCommand,
    VehicleLimits,
    altitude_bound,
    autopilot_takeover,
    battery_failsafe,
    commanded_action,
    fence_failsafe,
    landed_while_down,
    limit_refusal,
    lost_link_failsafe,
    speed_bound,
)
from baton.drone.sequencer import Sequencer, TakeoverDue, cut_off_outcome
from baton.drone.store import DroneState, Intent
from baton.rpc.errors import StatusError
from baton.rpc.labels import label
from baton.rpc.methods import Method, drone_api, path
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2

# A drone restarted mid-mission counts its master as seen this long after the
# restart: time for the controllers to re-connect (their back-off reaches
# 1 s), after which a master that did not come back is lost.
RESTART_GRACE_S = 5.0
# A master not seen since the drone started counts as seen this long after
# the drone first saw any controller: the controllers come up one by one, and
# a takeover at the start must not go to whichever came first. One that never
# comes up is then lost, and the mission goes on without it.
START_GRACE_S = 10.0
# How often the drivers look whether the master is lost, a preparation is due, or a
# failsafe is due (a fraction of the takeover time).
WATCH_TICK_S = 0.05


# A picture is taken where the vehicle is and its reply says where: it needs the vehicle
# as a Mobility call does, the connection for the place, and after a restart the first
# look for whether the autopilot moved the vehicle while the drone service was down.
PLACED = path("Camera.TakePicture")


def needs_vehicle(route: Method) -> bool:
    """Whether a call of ``route`` needs the vehicle connected and, after a restart with
    it in the air, looked at first: Mobility and Gimbal calls reach it (the gimbal is
    commanded over the vehicle's link); a picture is taken where it is (``PLACED``)."""
    return route.service in ("Mobility", "Gimbal") or route.path == PLACED


@dataclass(frozen=True)
class Admitted:
    """A request the drone admitted: answered from the cache (``cached``), or to execute.

    ``intent`` is what the store keeps of it until its outcome is booked (a
    restart finds it cut off), with ``kept``, the master's own answers (and
    adopted replies), in one transaction; ``first`` the handover record the
    request completed as its new master's first, if it did.
    """

    cached: CachedReply | None
    kept: tuple[CachedReply, ...]
    first: drone_pb2.HandoverRecord | None
    # Admitted but refused before execution (failsafe, a bound): the request's
    # outcome, booked like a failure of the vehicle, nothing executed.
    refused: StatusError | None = None
    intent: Intent | None = None  # None for one answered from the cache


@dataclass(frozen=True)
class Kept:
    """What the durable store keeps across a restart (``store.py``): the master, its
    handovers, the counters (last reqnr, executed, duplicates, rejected), the replies,
    the audit, the script lines fired, the watermark; the modes the drone last
    commanded the vehicle, the failsafe it was in, and the request it was executing."""

    master: int
    handovers: Sequence[drone_pb2.HandoverRecord]
    counts: tuple[int, int, int, int]
    replies: Sequence[CachedReply]
    audit: Sequence[drone_pb2.AuditEntry]
    fired_script: Sequence[int]
    watermark: int
    commanded: Any = None  # as ``DroneCore.kept_command`` gave it (an older file: a list)
    failsafe: Failsafe | None = None
    executing: Intent | None = None

    @classmethod
    def of(cls, state: DroneState, commanded: Any, failsafe: Failsafe | None) -> Kept:
        """What a restarted drone resumes from: the store's ``state``, the vehicle command
        it kept (``DroneCore.kept_command``) and the failsafe the vehicle was in."""
        c = state.counters
        counts = (c.last_reqnr, c.executed, c.duplicates, c.rejected)
        return cls(
            c.master,
            c.handovers,
            counts,
            state.replies,
            state.audit,
            c.fired_script,
            c.watermark,
            commanded,
            failsafe,
            state.executing,
        )


class DroneCore:
    """The drone's whole decision state: the ``Sequencer`` and the sightings of controllers."""

    def __init__(
        self,
        seq: Sequencer,
        takeover_after_s: float = 0.0,
        safety: SafetyParams | None = None,
        watch: DroneWatch | None = None,
    ) -> None:
        self.seq = seq
        self.safety = safety or SafetyParams()
        # The invariants checked at every admitted request (None: not checked).
        self.watch = watch
        # The failsafe the vehicle is in (None: the mission has it), and when a usable
        # controller was last there (None: not looked yet).
        self.failsafe: Failsafe | None = None
        self.last_usable: float | None = None
        # The bounds the autopilot said at its last read (``limits_read``): a call is
        # refused beyond the smaller of them and the configured ones.
        self.vehicle_limits = VehicleLimits()
        # Whether the vehicle was out of the fence at the last look (a breach acts once).
        self.out_of_fence = False
        # What the drone last commanded the vehicle (None: nothing yet, no mission flies
        # it), the vehicle's mode at the last look, and whether a ground station took it
        # over (its override: the station commands the vehicle until a resume).
        self.vehicle_command: VehicleCommand | None = None
        self.mode: ModeSeen | None = None
        self.station_override = False
        # The state file said the vehicle was in the air when the drone stopped: its
        # first sight since says whether it landed meanwhile (``restore_command``).
        self.airborne_before_restart = False
        # The master is lost after this long unseen; 0: never (only an operator's takeover).
        self.takeover_after_s = takeover_after_s
        self.routes: Mapping[str, Method] = drone_api()
        # When each controller was last seen; absent until it first is.
        self.last_seen: dict[int, float] = {}
        # The operator's pause, the end of the mission, every command (operator.py).
        self.operator = Operator()
        # When each controller last served: held its Connect stream or sent a request.
        self.last_served: dict[int, float] = {}
        # When the first controller was seen since the drone started (the start-up
        # grace runs from then); None until one is.
        self.first_seen: float | None = None

    # -- sightings -------------------------------------------------------------------

    def seen(self, controller_id: int, now: float) -> None:
        """``controller_id`` was seen at ``now``: it sent a request, or a stream of it ended."""
        if controller_id in self.seq.ring:
            self.last_seen[controller_id] = now
            self.last_usable = max(self.last_usable or now, now)

    def sighted(self, now: float, holders: Iterable[int]) -> set[int]:
        """The controllers holding a stream now (``holders``), noted as seen now."""
        reachable = set(holders)
        for cid in reachable:
            self.last_seen[cid] = now
        if reachable and self.first_seen is None:
            self.first_seen = now
        return reachable

    @property
    def serve_within_s(self) -> float:
        """How long a master may go without serving before it is lost (0: never)."""
        if self.takeover_after_s <= 0:
            return 0.0
        return max(self.takeover_after_s, self.seq.prepare_timeout_s)

    @property
    def unseen_from(self) -> float | None:
        """When a master not seen since the drone started counts as seen (the end of the
        start-up grace); None while no controller was seen."""
        return None if self.first_seen is None else self.first_seen + START_GRACE_S

    def down_for(self, controller_id: int, now: float) -> float | None:
        """How long ``controller_id``, holding no stream, has been unseen (the start-up
        grace counted as a sighting); None if no controller was seen yet."""
        seen = self.last_seen.get(controller_id, self.unseen_from)
        return None if seen is None else max(0.0, now - seen)

    @staticmethod
    def takers(reachable: set[int], in_range: set[int] | None) -> set[int]:
        """Who may take a lost master over: the reachable controllers, and with a handover
        policy (``in_range`` not None) only those in range of the vehicle."""
        return reachable if in_range is None else reachable & in_range

    def takeover_due(
        self,
        now: float,
        holders: Iterable[int],
        connected: Iterable[int],
        in_range: set[int] | None,
    ) -> TakeoverDue | None:
        """Whether the master is lost now, and who takes over (``Sequencer.takeover_due``):
        ``holders`` hold a stream now, ``connected`` a Connect stream."""
        for cid in connected:
            self.last_served[cid] = now
        reachable = self.takers(self.sighted(now, holders), in_range)
        return self.seq.takeover_due(
            now,
            reachable,
            self.last_seen,
            self.takeover_after_s,
            self.unseen_from,
            self.last_served,
            self.serve_within_s,
        )

    def takeover_owed(self, controller_id: int) -> drone_pb2.TakeOver | None:
        """The TakeOver to tell ``controller_id`` again on a new standby stream: it is the
        taker and has sent no request since (the stream that carried it may have broken)."""
        seq = self.seq
        if controller_id != seq.master or not seq.handovers:
            return None
        record = seq.handovers[-1]
        if record.kind != drone_pb2.HANDOVER_KIND_TAKEOVER or record.first_request_at:
            return None
        return take_over_event(record, seq.cache.watermark)

    # -- the safety net ---------------------------------------------------------------

    def limits_read(self, limits: VehicleLimits) -> None:
        """The autopilot said its bounds (read at connect and after its reboot); kept until
        it says them again (the link lost or the autopilot rebooting changes none)."""
        self.vehicle_limits = limits

    def bounds(self) -> tuple[Bound, Bound]:
        """The bounds in force, speed and altitude (``safety.speed_bound``,
        ``safety.altitude_bound``)."""
        return (
            speed_bound(self.safety, self.vehicle_limits),
            altitude_bound(self.safety, self.vehicle_limits),
        )

    def failsafe_due(
        self,
        now: float,
        holders: Iterable[int],
        in_range: set[int] | None,
        airborne: bool,
        nearest: int | None = None,
    ) -> Failsafe | None:
        """The lost-link failsafe due now (``safety.lost_link_failsafe``), or None: none is
        due while the vehicle is on the ground, is already in failsafe, or a controller it
        could make master (``takers``: holding a stream, in range with a policy) is there.
        ``nearest`` is the station nearest the vehicle, for ``nearest_station``."""
        if self.takers(set(holders) & set(self.seq.ring), in_range):
            self.last_usable = now
            return None
        if self.last_usable is None or not airborne:
            if self.last_usable is not None and self.last_usable > now:
                return None  # a restart's grace runs
            # Counted from the first look in the air: a drone restarted mid-flight, or
            # a vehicle that took off, waits the whole lost_link time.
            self.last_usable = now
            return None
        if self.failsafe is not None:
            return None
        return lost_link_failsafe(now, self.last_usable, self.safety, nearest)

    def failsafe_check(
        self,
        now: float,
        airborne: bool,
        battery_percent: float,
        position: api.Position | None,
        seen: ModeSeen,
        holders: Iterable[int],
        in_range: set[int] | None,
        nearest: int | None = None,
    ) -> Failsafe | None:
        """A look at the vehicle: the failsafe due now, in this order of precedence: the
        battery (``battery_due``), the fence at ``position`` (``fence_due``; None: the
        position is not watched), the autopilot's takeover with the vehicle as it reports
        itself (``autopilot_due``), the lost link (``failsafe_due``, none while already
        in a failsafe). ``nearest`` is the station nearest the vehicle."""
        battery = self.battery_due(now, battery_percent, airborne, nearest)
        if battery is not None:
            return battery
        if position is not None:
            breach = self.fence_due(now, position, airborne)
            if breach is not None:
                return breach
        taken_over = self.autopilot_due(now, seen)
        if taken_over is not None or self.failsafe is not None:
            return taken_over
        return self.failsafe_due(now, holders, in_range, airborne, nearest)

    def battery_due(
        self, now: float, percent: float, airborne: bool, nearest: int | None = None
    ) -> Failsafe | None:
        """The battery failsafe due now (``safety.battery_failsafe``), or None: none on the
        ground, nor while the vehicle already returns or lands for a failsafe; a lost-link
        hold is ended by it (the vehicle must come back before the battery runs out)."""
        if not airborne:
            return None
        held = self.failsafe
        if held is not None and (held.cause == "battery" or held.action != "hold"):
            return None
        return battery_failsafe(now, percent, self.safety, nearest)

    def fence_due(self, now: float, position: api.Position, airborne: bool) -> Failsafe | None:
        """The fence failsafe due now (``safety.fence_failsafe``), or None: none on the
        ground or while in a failsafe already, and once per breach: a vehicle still out
        after an operator's resume is not put back in failsafe until it was inside."""
        due = fence_failsafe(now, position, self.safety.fence) if airborne else None
        if due is None and (position.latitude_deg or position.longitude_deg):
            self.out_of_fence = False
        if self.failsafe is not None or self.out_of_fence:
            return None
        return due

    def autopilot_due(self, now: float, seen: ModeSeen) -> Failsafe | None:
        """The autopilot's takeover due now (``safety.autopilot_takeover``) with the vehicle
        as it reports itself (``seen``), or None: none is due while no mission flies the
        vehicle (nothing commanded yet), in a failsafe, while paused or ended by an
        operator, or after a ground station's override."""
        self.mode = seen
        command = self.vehicle_command
        operator = self.operator
        if command is None or self.station_override:
            return None
        due = None
        if self.airborne_before_restart:
            # Until the vehicle is seen flying, or a failsafe holds it: due at every look
            # (the driver looks again under its lock before it enters the failsafe).
            due = landed_while_down(now, command, seen)
            self.airborne_before_restart = due is not None and self.failsafe is None
        if due is None:
            self.vehicle_command, due = autopilot_takeover(now, command, seen)
        if self.failsafe is not None or operator.paused is not None or operator.ended is not None:
            return None
        return due

    def kept_command(self) -> dict[str, Any] | None:
        """What the state file keeps of the vehicle command: its actions, and whether the
        vehicle was seen in the air since (a restarted drone holds the vehicle to it,
        ``restore_command``); None while nothing was commanded."""
        command = self.vehicle_command
        if command is None:
            return None
        # Not looked at since a restart, the vehicle is still last known in the air.
        airborne = command.airborne or self.airborne_before_restart
        return {"actions": list(command.actions), "airborne": airborne}

    def restore_command(self, kept: Any, now: float) -> None:
        """The vehicle command the state file kept (``kept_command``; a list of actions in
        an older file), its modes read from the restart grace on (the telemetry comes
        back meanwhile). Seen in the air before the restart, the vehicle's first sight
        decides whether it landed meanwhile (``safety.landed_while_down``)."""
        if kept is None:
            return
        if not isinstance(kept, dict):
            kept = {"actions": kept}
        actions = tuple(str(a) for a in kept["actions"])
        self.vehicle_command = VehicleCommand(actions, now + RESTART_GRACE_S)
        self.airborne_before_restart = bool(kept.get("airborne", False))

    def vehicle_unseen(self) -> None:
        """The vehicle did not say its state at the last look (``VehicleCommand.unseen``)."""
        if self.vehicle_command is not None:
            self.vehicle_command = self.vehicle_command.unseen()

    def commanding(self, action: str | None, now: float) -> None:
        """The drone is sending the vehicle a command for ``action`` (``safety.FLY``,
        ``HOLD``, ``LAND``, ``RTL``; None: one that changes no mode): either mode may
        follow until ``commanded``."""
        if action is None:
            return
        command = self.vehicle_command
        if command is None:
            # The first command: a vehicle the last look saw in the air flies from now
            # (a mission may find it flying), as a look would have said had one come.
            seen = self.mode
            airborne = seen is not None and seen.armed and seen.in_air
            self.vehicle_command = VehicleCommand((action,), now, airborne=airborne)
        else:
            self.vehicle_command = command.commanding(action, now)

    def sending(self, method: str, now: float) -> str | None:
        """A call of ``method`` is about to reach the vehicle: the action a Mobility command
        commands (``VEHICLE_ACTIONS``; None for a read, the camera, or a command that
        changes no mode), noted as being sent (``commanding``)."""
        route = self.routes[method]
        action = VEHICLE_ACTIONS.get(route.name) if route.service == "Mobility" else None
        self.commanding(action, now)
        return action

    def acknowledged(self, method: str, payload: bytes, now: float) -> bool:
        """The vehicle acknowledged a call of ``method``: a Mobility command's modes are
        expected from now (``commanded``) and the leg a resume flies on follows it
        (``Operator.executed``). True if what is expected changed (the state file keeps
        it, ``kept_command``)."""
        route = self.routes[method]
        if route.service != "Mobility":
            return False
        self.operator.executed(route.name, payload)
        return self.commanded(VEHICLE_ACTIONS.get(route.name), now)

    def commanded(self, action: str | None, now: float) -> bool:
        """The vehicle accepted the command for ``action`` (``VehicleCommand.commanded``).
        True if what is expected changed (the drone keeps it in its state file)."""
        if action is None:
            return False
        before = self.vehicle_command
        if before is None:
            self.vehicle_command = VehicleCommand((action,), now)
            return True
        self.vehicle_command = before.commanded(action, now)
        return before.actions != (action,)

    def station_took_over(self) -> None:
        """A ground station's override (passed to the autopilot as it came): the vehicle's
        mode is the station's until an operator resumes."""
        self.station_override = True

    def enter_failsafe(self, failsafe: Failsafe) -> None:
        """The vehicle is in ``failsafe`` from now: requests are refused until a resume."""
        self.failsafe = failsafe
        if failsafe.cause == "fence":
            self.out_of_fence = True
        action = commanded_action(failsafe.action) if failsafe.drone_acts else None
        if action is not None:
            self.vehicle_command = VehicleCommand((action,), failsafe.since)

    def resume_mission(self, now: float) -> tuple[Failsafe | None, OperatorCommand]:
        """An operator gives the mission the vehicle back (``Operator.resume``: raises
        StatusError if nothing holds it): the pause and the failsafe cleared (the
        failsafe returned; None if there was none), the lost-link time counted afresh
        from ``now``."""
        taken = self.operator.resume(now, self.seq.last_reqnr, self.failsafe)
        cleared, self.failsafe = self.failsafe, None
        self.last_usable = now
        # The vehicle goes on in the mode it is in (the autopilot's, a station's) until
        # the mission's next command: resumed, that mode is not a takeover.
        command, self.station_override = self.vehicle_command, False
        if command is not None:
            accepted = "" if self.mode is None else self.mode.mode
            self.vehicle_command = VehicleCommand(command.actions, now, accepted=accepted)
        return cleared, taken

    def operator_command(
        self, command: str, now: float, action: str = "", note: str = ""
    ) -> tuple[OperatorCommand, Failsafe | None]:
        """An operator's command (``operator.COMMANDS``) between two requests: what was
        taken, and the failsafe a resume cleared (None: none). An abort returns home
        unless ``action`` says land. StatusError to refuse it: nothing changes."""
        after = self.seq.last_reqnr
        if command == "pause":
            return self.operator.pause(now, after, note=note), None
        if command == "resume":
            cleared, taken = self.resume_mission(now)
            return taken, cleared
        return self.operator.end(command, action or "rtl", now, after, note), None

    def holds(self, request: drone_pb2.InvokeRequest) -> bool:
        """Whether ``request`` waits at the drone before admission: the mission is paused
        and it is the master's next (``Operator.holds``)."""
        seq = self.seq
        return self.operator.holds(request.controller_id, request.reqnr, seq.master, seq.last_reqnr)

    def refusal(self, method: str, payload: bytes) -> StatusError | None:
        """Why an admitted request is not executed: the mission ended by an operator, the
        vehicle in failsafe, a bound of the vehicle it asks beyond, or a move out of the
        fence; None to execute it. A payload that does not parse is left to the
        execution, which refuses it."""
        route = self.routes.get(method)
        name = route.rpc if route is not None else method
        ended = self.operator.refusal(name)
        if ended is not None:
            return ended
        if self.failsafe is not None:
            return self.failsafe.refusal(name)
        if route is None:
            return None
        try:
            message = route.parse(payload)
        except StatusError:
            return None
        return limit_refusal(route.rpc, message, self.safety, self.vehicle_limits) or move_refusal(
            route.rpc, message, self.safety.fence
        )

    def unreachable(self, method: str, vehicle_connected: bool, why: str) -> StatusError | None:
        """UNAVAILABLE for a call that needs the vehicle (``needs_vehicle``) while the
        vehicle is not connected (``why``), or while a drone restarted with the vehicle in
        the air has not looked at it yet (its autopilot may have landed it or sent it home
        meanwhile: ``autopilot_due`` decides at the first look): nothing reaches it, so
        the number stays unused (``books``); None otherwise."""
        route = self.routes.get(method)
        if route is None or not needs_vehicle(route):
            return None
        if not vehicle_connected:
            return StatusError(
                grpc.StatusCode.UNAVAILABLE, f"{method}: the vehicle {why} is not connected"
            )
        if self.airborne_before_restart and self.mode is None:
            return StatusError(
                grpc.StatusCode.UNAVAILABLE,
                f"{method}: the vehicle was in the air when the drone service stopped and "
                "the restarted service has not seen its flight state yet; nothing was executed",
            )
        return None

    # -- requests --------------------------------------------------------------------

    def master_answers(
        self, reqnr: int, answers: Sequence[drone_pb2.RetainedReply]
    ) -> list[CachedReply]:
        """The calls a master answered itself, sent along with request ``reqnr``: Clock
        replies and calls its program gave up on; INVALID_ARGUMENT for anything else."""
        kept = []
        for answer in answers:
            route = self.routes.get(answer.method)
            if route is None or (route.answered_by_drone and not answer.given_up):
                raise StatusError(
                    grpc.StatusCode.INVALID_ARGUMENT,
                    f"Invoke reqnr {reqnr}: master_answers holds reqnr {answer.reqnr} "
                    f"as {answer.method!r}, which is neither a Clock method nor a call given "
                    "up by the program; only what a controller answered itself is sent along",
                )
            kept.append(CachedReply.from_proto(answer))
        return kept

    def admit(
        self,
        request: drone_pb2.InvokeRequest,
        digest: bytes,
        received_at: float,
    ) -> Admitted:
        """Admits a request (raises StatusError to refuse it): a sighting of its sender,
        its master answers checked, ``Sequencer.admit``, the master's word on a
        preparation, the first request of a new master; then what to keep with it."""
        seq, cid = self.seq, request.controller_id
        self.seen(cid, received_at)
        answers = self.master_answers(request.reqnr, request.master_answers)
        if request.framed_after_epoch > request.epoch:
            # The message a mastership builds on is never of a newer mastership.
            raise StatusError(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"Invoke reqnr {request.reqnr}: framed_after_epoch "
                f"{request.framed_after_epoch} is newer than the request's epoch "
                f"{request.epoch}; a master's own messages follow a message of its epoch or "
                "an older one",
            )
        cached = seq.admit(
            cid,
            request.epoch,
            request.reqnr,
            request.method,
            digest,
            request.watermark_reqnr,
            answers,
        )
        self.last_served[cid] = received_at  # admitted: from the master, in its epoch
        if self.watch is not None:
            self._check(cid, request.epoch, request.reqnr)
        if request.HasField("preparation"):
            seq.note_progress(cid, request.epoch, request.preparation)
        first = seq.note_request(cid, received_at)
        if request.HasField("framed_after_lognr"):
            framed_after = (request.framed_after_lognr, request.framed_after_epoch)
            seq.note_framing(cid, request.epoch, framed_after)
        if cached is not None:
            return Admitted(cached, (), first)
        kept = seq.keep(answers) + tuple(
            seq.adopt(cid, request.epoch, request.adopted_from_reqnr, request.reqnr)
        )
        refused = self.refusal(request.method, request.payload)
        intent = Intent(request.reqnr, request.method, digest, cid, received_at)
        return Admitted(None, kept, first, refused, intent)

    def _check(self, cid: int, epoch: int, reqnr: int) -> None:
        """The drone's invariants after an admission (``invariants.DroneWatch``)."""
        assert self.watch is not None
        seq = self.seq
        problem = self.watch.accepted(epoch, cid, reqnr) or self.watch.moved(
            seq.epoch, seq.last_reqnr, seq.cache.watermark
        )
        if problem is not None:
            raise InvariantBroken(problem)

    @staticmethod
    def books(error: StatusError) -> bool:
        """Whether a failure after admission is the request's outcome: all but UNAVAILABLE,
        which means nothing reached the vehicle (the number stays unused)."""
        return error.code is not grpc.StatusCode.UNAVAILABLE

    # -- moving the master: events, each returning its effects (effects.py) -----------

    def hand_over(
        self,
        new_master: int,
        trigger: drone_pb2.HandoverTrigger.ValueType,
        now: float,
        takeover: bool = False,
        reason: str = "",
        position: api.Position | None = None,
    ) -> list[DroneEffect]:
        """Moves the master to ``new_master`` now, between two requests: by takeover when
        asked or when the master could not send its log (``must_take_over``), else the
        paper's cooperative handover. StatusError if ``new_master`` may not be made
        master (unknown, or already the master)."""
        if self.must_take_over(new_master, takeover):
            return self.take_over(new_master, trigger, now, reason=reason, position=position)
        record = self.seq.switch(new_master, trigger, now, reason=reason, position=position)
        return [SaveCounters(), Switched(record)]

    def take_over(
        self,
        new_master: int,
        trigger: drone_pb2.HandoverTrigger.ValueType,
        now: float,
        lost_at: float = 0.0,
        reason: str = "",
        position: api.Position | None = None,
        lost: int | None = None,
    ) -> list[DroneEffect]:
        """Switches to ``new_master`` by takeover and tells it on its standby stream.
        ``lost`` is the controller whose log is given up (``TakeoverDue.lost``; None: the
        master, or the lost old master of the last switch when the master is granted
        again)."""
        record = self.seq.switch(
            new_master,
            trigger,
            now,
            takeover=True,
            lost_at=lost_at,
            reason=reason,
            position=position,
            lost=lost,
        )
        told = take_over_event(record, self.seq.cache.watermark)
        return [SaveCounters(), Switched(record), TellTakeOver(record, told, lost_at)]

    def handover_call(
        self,
        new_master: int,
        prepared: bool,
        takeover: bool,
        master_connected: bool,
        now: float,
    ) -> list[DroneEffect]:
        """An operator's Handover: prepared when asked (and not a takeover) and the master
        can prepare (``can_prepare``: it holds its Connect stream to hear the
        PrepareHandover); else at once, as ``hand_over``. StatusError to refuse it."""
        self.seq.check_known(new_master)
        rpc = drone_pb2.HANDOVER_TRIGGER_RPC
        if prepared and not takeover and self.can_prepare(master_connected, new_master):
            return [Preparing(self.seq.prepare(new_master, rpc, now))]
        return self.hand_over(new_master, rpc, now, takeover)

    def prepared_outcome(self, target: int, started_at: float) -> drone_pb2.HandoverRecord:
        """How the prepared handover to ``target`` begun at ``started_at`` ended, once it is
        no longer under way: its record, or ABORTED if another switch replaced it."""
        record = self.seq.handovers[-1]
        if record.prepare_started_at != started_at:
            raise StatusError(
                grpc.StatusCode.ABORTED,
                f"the handover to controller {target} being prepared was replaced by "
                f"another switch (to controller {record.new_master}, "
                f"{label(drone_pb2.HandoverKind, record.kind)})",
            )
        return record

    def policy_handover(
        self,
        decision: Decision,
        decided_for: int,
        master_connected: bool,
        now: float,
        position: api.Position | None = None,
    ) -> tuple[str, list[DroneEffect]]:
        """The handover policy's ``decision`` (made while ``decided_for`` was master),
        carried out now (``policy.handover_step``): what was done, and its effects."""
        target, seq = decision.target, self.seq
        assert target is not None
        preparing = seq.preparing
        step = handover_step(
            decision,
            decided_for,
            seq.master,
            self.can_prepare(master_connected, target),
            None if preparing is None else preparing.target,
        )
        trigger = drone_pb2.HANDOVER_TRIGGER_POLICY
        if step == SWITCH:
            effects = self.hand_over(
                target, trigger, now, decision.takeover, decision.reason, position
            )
            return ("takeover" if decision.takeover else step), effects
        if step == PREPARE:
            notice = seq.prepare(target, trigger, now, reason=decision.reason, position=position)
            return step, [Preparing(notice)]
        return step, []

    def master_watch(
        self,
        now: float,
        holders: Iterable[int],
        connected: Iterable[int],
        in_range: set[int] | None,
        position: api.Position | None = None,
    ) -> list[DroneEffect]:
        """A tick of the master watch: the master taken over if it is lost
        (``takeover_due``), then a preparation past its deadline forced."""
        effects: list[DroneEffect] = []
        due = self.takeover_due(now, holders, connected, in_range)
        if due is not None:
            effects += self.take_over(
                due.new_master,
                drone_pb2.HANDOVER_TRIGGER_LOST,
                now,
                due.lost_at,
                position=position,
                lost=due.lost,
            )
        forced = self.seq.preparation_expired(now)
        if forced is not None:
            effects += [SaveCounters(), Switched(forced)]
        return effects

    def preparation_word(
        self,
        controller_id: int,
        epoch: int,
        progress: drone_pb2.PreparationProgress,
        now: float,
    ) -> list[DroneEffect]:
        """The master's word on its preparation between requests: the master moves now if
        the target caught up (``Sequencer.progress_between``)."""
        record = self.seq.progress_between(controller_id, epoch, progress, now)
        return [] if record is None else [SaveCounters(), Switched(record)]

    def fresh_self_connect(
        self, controller_id: int, given_up_epoch: int, now: float
    ) -> list[DroneEffect]:
        """A Connect of a fresh self of the master that gave its mastership up, under the
        lock (checked again: a second Connect of it finds the epoch moved on): it is
        granted a new epoch by a takeover of its earlier self
        (``Sequencer.fresh_self_due``). Its Connected says so; nothing is told on its
        standby stream."""
        if not self.seq.fresh_self_due(controller_id, 0, given_up_epoch):
            return []
        record = self.seq.take_over_from_earlier_self(controller_id, now)
        said = Note(
            "warning",
            "master's fresh self takes over from its earlier self",
            {"controller": controller_id, "given_up_epoch": given_up_epoch, "epoch": record.epoch},
        )
        return [SaveCounters(), Switched(record), said]

    def served(
        self,
        controller_id: int,
        reqnr: int,
        method: str,
        digest: bytes,
        reply: bytes,
        received_at: float,
        now: float,
        error: StatusError | None = None,
    ) -> list[DroneEffect]:
        """A request's outcome (``error``: a failure booked): booked, then the script's
        handover or preparation after it, if any (``Sequencer.served``)."""
        served = self.seq.served(
            controller_id, reqnr, method, digest, reply, received_at, now, error
        )
        effects: list[DroneEffect] = [Book(served)]
        if served.skipped is not None:
            fields = {
                "new_master": served.skipped.new_master,
                "after_reqnr": reqnr,
                "script_line": served.skipped.line,
            }
            effects.append(Note("warning", "scripted handover skipped: already the master", fields))
        if served.handover is not None:
            effects.append(Switched(served.handover))
        if served.prepare is not None:
            effects.append(Preparing(served.prepare))
        return effects

    def failed(
        self,
        controller_id: int,
        reqnr: int,
        method: str,
        digest: bytes,
        received_at: float,
        now: float,
        error: StatusError,
    ) -> list[DroneEffect]:
        """An admitted request failed: its outcome booked (``served``) unless nothing
        reached the vehicle (``books``): then its intent is abandoned, the number unused."""
        if not self.books(error):
            return [Abandon()]
        return self.served(controller_id, reqnr, method, digest, b"", received_at, now, error)

    # -- masters ---------------------------------------------------------------------

    def must_take_over(self, new_master: int, takeover: bool) -> bool:
        """Whether a switch to ``new_master`` is a takeover: when asked, or when the master
        could not send its log (``Sequencer.handover_must_take_over``)."""
        return takeover or self.seq.handover_must_take_over(new_master)

    def can_prepare(self, master_connected: bool, new_master: int) -> bool:
        """Whether a handover to ``new_master`` can be prepared: the master holds its
        Connect stream (to hear the PrepareHandover) and could send its log."""
        return master_connected and not self.seq.handover_must_take_over(new_master)

    # -- the master's Connect stream ---------------------------------------------------

    def connected(
        self, request: drone_pb2.ConnectRequest, batch_bytes: int = RETAINED_BATCH_BYTES
    ) -> tuple[drone_pb2.Connected, list[list[CachedReply]]] | None:
        """What a Connect (admitted: ``Sequencer.admit_connect``) carries first, if its
        controller is the master: the Connected grant, then the replies the drone
        retains above what it holds (``holds_reqnr``), in batches of about
        ``batch_bytes`` (the master answers its program from the first while the rest
        crosses). None for a controller that is not the master (owed a notice). A
        taker's first Connect says what its messages follow (``taker_connected``),
        unless what it holds is of a framing an earlier takeover replaced
        (``Sequencer.replaced_framing``): its Connected says from where, and it
        rejoins refusing that framing before it acts."""
        seq = self.seq
        if request.controller_id != seq.master:
            return None
        replaced = None
        if seq.granted_by_takeover:
            replaced = seq.replaced_framing(request.holds_lognr, request.holds_lognr_epoch)
        if replaced is None:
            seq.taker_connected(request)  # not on a framing it will refuse
        controller_id = request.controller_id
        retained = seq.replies_for_master(request.holds_reqnr)
        grant = drone_pb2.Connected(
            master=controller_id,
            last_reqnr=seq.last_reqnr,
            epoch=seq.epoch,
            retained_through=retained[-1].reqnr if retained else 0,
            takeover=seq.granted_by_takeover,
            watermark_reqnr=seq.cache.watermark,
            takeover_epoch=seq.takeover_epoch,
            grant=seq.signed_grant(seq.epoch),
        )
        if replaced is not None:
            grant.replaced_from_lognr, grant.replaced_by_epoch = replaced
        return grant, retained_batches(retained, batch_bytes)

    def stream_event(
        self, controller_id: int, sent_prepare: drone_pb2.PrepareHandover | None
    ) -> drone_pb2.PrepareHandover | drone_pb2.HandoverNotice | None:
        """The next event for ``controller_id``'s Connect stream, which sent
        ``sent_prepare`` last: the PrepareHandover of a preparation under way, to the
        master, once; else the handover notice owed to it, after which the stream ends
        (``Sequencer.delivered`` once it is written); None: nothing now."""
        seq = self.seq
        preparing = seq.preparing
        if (
            preparing is not None
            and controller_id == seq.master
            and preparing.notice is not sent_prepare
        ):
            return preparing.notice
        return seq.pending.get(controller_id)

    def delivered(self, controller_id: int, notice: drone_pb2.HandoverNotice) -> None:
        """The handover ``notice`` was written on ``controller_id``'s stream: no longer owed."""
        self.seq.delivered(controller_id, notice)

    def operator_word(self) -> drone_pb2.OperatorWord:
        """The operator's pause as the master's Connect stream says it (empty: not paused)."""
        paused = self.operator.paused
        return drone_pb2.OperatorWord(paused="" if paused is None else paused.reason)

    # -- a restart -------------------------------------------------------------------

    def resume(
        self,
        now: float,
        master: int,
        handovers: Iterable[drone_pb2.HandoverRecord],
        counts: tuple[int, int, int, int],
        replies: Iterable[CachedReply],
        audit: Iterable[drone_pb2.AuditEntry],
        fired_script: Iterable[int],
        watermark: int,
    ) -> None:
        """Takes back what the durable store kept (``Sequencer.resume``). The master of a
        mission in progress was there before the restart: it counts as seen at the end
        of the restart grace, so it is lost if it does not come back."""
        self.seq.resume(master, handovers, counts, replies, audit, fired_script, watermark)
        if self.seq.last_reqnr or self.seq.handovers:
            self.last_seen[master] = self.last_served[master] = now + RESTART_GRACE_S
            # The lost-link time too counts from the end of the grace: the controllers
            # re-connect to a restarted drone meanwhile.
            self.last_usable = now + RESTART_GRACE_S

    def restarted(self, now: float, kept: Kept) -> list[DroneEffect]:
        """The drone started again from what its store kept: the modes it commanded read
        after the restart grace (the telemetry comes back meanwhile), the failsafe it
        was in, ``resume``; then the request the restart cut off (``cut_off``): a read
        abandoned (executed again when re-sent), anything else booked with its failure."""
        self.restore_command(kept.commanded, now)
        if kept.failsafe is not None:
            self.enter_failsafe(kept.failsafe)
        self.resume(
            now,
            kept.master,
            kept.handovers,
            kept.counts,
            kept.replies,
            kept.audit,
            kept.fired_script,
            kept.watermark,
        )
        cut = kept.executing
        if cut is None:
            return []
        error = self.cut_off(cut)
        if error is None:
            read = Note(
                "info", "read cut off by the restart: will execute again", {"reqnr": cut.reqnr}
            )
            return [Abandon(), read]
        said: dict[str, object] = {"reqnr": cut.reqnr, "method": cut.method}
        booked = self.served(
            cut.controller_id, cut.reqnr, cut.method, cut.digest, b"", cut.received_at, now, error
        )
        return [Note("warning", "request cut off by the restart", said), *booked]

    def cut_off(self, intent: Intent) -> StatusError | None:
        """The outcome of a request a restart cut off while it executed: None for a read
        (executed again when re-sent), else the failure to book (``cut_off_outcome``)."""
        route = self.routes.get(intent.method)
        return cut_off_outcome(intent.method, intent.reqnr, route is not None and route.is_read)
