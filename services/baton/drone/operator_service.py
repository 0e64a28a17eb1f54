"""The operator's commands on the drone service: Pause, Resume, Abort, LandNow.

A driver of ``operator.py``'s decisions (held by ``DroneCore``): each handler checks
the caller's certificate, takes the execution lock (a command falls between two
requests), asks the core, saves what it decided in the state file, then tells the
vehicle and records what it did. ``wait_resumed`` is where a request of a paused
mission waits before admission (``DroneService.invoke``).

Only the operator's certificate (``spiffe://baton/operator``) may command, under
mutual TLS. On an insecure port (``--insecure``) anyone who reaches the port may:
what guards them then is the network alone (docs/operating.md, "Operator commands").
"""

from __future__ import annotations

import asyncio
import time
from typing import TYPE_CHECKING

import grpc

from baton.drone.mobility_api import command_action
from baton.drone.operator import Operator, OperatorCommand
from baton.drone.safety import Failsafe, commanded_action
from baton.rpc.errors import StatusError, abort_with
from baton.rpc.tls import OPERATOR, refused
from baton.tasks import TaskSet
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2

if TYPE_CHECKING:
    from baton.drone.service import DroneService

# The state file's key of the operator's state (store.save_commanded).
OPERATOR_KEY = "operator"
RULE = f"only an operator ({OPERATOR.uri}) may pause, resume or end the mission"


class OperatorCommands:
    """Drone.Pause, Resume, Abort and LandNow for one ``DroneService``."""

    def __init__(self, service: DroneService) -> None:
        self.service = service
        # Set when a pause ends (a resume, an abort, a land-now); replaced at each pause.
        self._unpaused = asyncio.Event()
        self._unpaused.set()
        self._tasks = TaskSet()  # a ground station's pauses

    # -- a request of a paused mission ----------------------------------------------

    async def wait_resumed(self, request: drone_pb2.InvokeRequest) -> None:
        """Returns once ``request`` need not wait (``DroneCore.holds``): at once unless the
        mission is paused and it is the master's next. Its caller going away ends the
        wait, with nothing admitted."""
        while self.service.core.holds(request):
            paused = self.service.core.operator.paused
            self.service.log.info(
                "request waits: the mission is paused",
                controller=request.controller_id,
                reqnr=request.reqnr,
                method=request.method,
                paused=paused.reason if paused is not None else "",
            )
            await self._unpaused.wait()

    def keep_leg(self, before: bytes | None) -> None:
        """Keeps the leg a resume flies on in the state file when an executed command changed
        it from ``before`` (``DroneCore.acknowledged``), so a restarted drone's resume flies
        it on too."""
        if self.service.core.operator.leg != before:
            self._save()

    def _tell_master(self) -> None:
        """Wakes the master's Connect stream to say the pause began or ended."""
        self.service.streams.wake(self.service.seq.master)

    def waiting(self) -> dict[str, str]:
        """What the drone waits for because of an operator, for GetStatus.waiting."""
        paused = self.service.core.operator.paused
        if paused is None:
            return {}
        return {"paused": f"{paused.reason}: the master's next request waits for Resume"}

    # -- the handlers ---------------------------------------------------------------

    async def pause(
        self, request: drone_pb2.PauseRequest, context: grpc.aio.ServicerContext
    ) -> drone_pb2.OperatorReply:
        taken, _ = await self._command(context, "Pause", "pause", note=request.note)
        return drone_pb2.OperatorReply(command=taken)

    async def resume(
        self, request: drone_pb2.ResumeRequest, context: grpc.aio.ServicerContext
    ) -> drone_pb2.ResumeReply:
        taken, cleared = await self._command(context, "Resume", "resume")
        reply = drone_pb2.ResumeReply(command=taken)
        if cleared is not None:
            reply.cleared.CopyFrom(failsafe_proto(cleared))
        return reply

    async def abort(
        self, request: drone_pb2.AbortRequest, context: grpc.aio.ServicerContext
    ) -> drone_pb2.OperatorReply:
        taken, _ = await self._command(context, "Abort", "abort", request.action, request.note)
        return drone_pb2.OperatorReply(command=taken)

    async def land_now(
        self, request: drone_pb2.LandNowRequest, context: grpc.aio.ServicerContext
    ) -> drone_pb2.OperatorReply:
        taken, _ = await self._command(context, "LandNow", "land_now", note=request.note)
        return drone_pb2.OperatorReply(command=taken)

    def ground_station_paused(self, station: str, what: str) -> None:
        """A ground station's override (drone/gcs.py) pauses the mission, between two
        requests as any command; the station commands the vehicle itself. Called on the
        relay's datagram path: the pause is a task of its own."""
        self.service.core.station_took_over()  # before its command reaches the vehicle
        self._tasks.spawn(self._ground_station_pause(station, what), name="gcs-pause")

    async def _ground_station_pause(self, station: str, what: str) -> None:
        service = self.service
        async with service.execution_lock:
            try:
                taken = service.core.operator.pause(
                    time.time(), service.seq.last_reqnr, by=station, note=what
                )
            except StatusError as err:
                service.log.info("ground station override: not paused", reason=err.message)
                return
            self._unpaused = asyncio.Event()
            self._save()
            self._tell_master()
        service.log.warning("mission paused", by=taken.by, reason=taken.reason)

    # -- carrying a command out -----------------------------------------------------

    async def _command(
        self,
        context: grpc.aio.ServicerContext,
        name: str,
        command: str,
        action: str = "",
        note: str = "",
    ) -> tuple[drone_pb2.OperatorCommand, Failsafe | None]:
        """Checks the caller, decides under the execution lock (``DroneCore.
        operator_command``), saves, tells the vehicle (still under the lock: no request
        executes in between), and records what it did; with the failsafe a resume
        cleared."""
        service = self.service
        try:
            refusal = refused(context, service.authenticated, name, RULE, lambda w: w == OPERATOR)
            if refusal is not None:
                raise refusal
            async with service.execution_lock:
                taken, cleared = service.core.operator_command(command, time.time(), action, note)
                if command == "pause":
                    self._unpaused = asyncio.Event()
                if command == "resume":
                    service.save_failsafe()
                if cleared is not None:
                    service.log.warning("failsafe cleared by the operator", cause=cleared.cause)
                self._save()
                service.log.warning(
                    "operator command",
                    command=taken.command,
                    action=taken.action,
                    after_reqnr=taken.after_reqnr,
                    reason=taken.reason,
                )
                if taken.command != "pause":
                    self._unpaused.set()  # a waiting request goes on: executed, or refused
                self._tell_master()
                taken = await self._tell_vehicle(taken)
        except StatusError as err:
            service.log.warning("operator command rejected", command=name, reason=err.message)
            await abort_with(context, err)
        return command_proto(taken), cleared

    async def _tell_vehicle(self, taken: OperatorCommand) -> OperatorCommand:
        """Commands the vehicle what ``taken`` says, and records its answer."""
        vehicle, operator = self.service.vehicle, self.service.core.operator
        action = commanded_action(taken.action)
        try:
            self.service.core.commanding(action, time.time())
            if taken.action == "goto" and operator.leg is not None:
                await vehicle.Goto(api.GotoRequest.FromString(operator.leg))
            elif not await command_action(vehicle, taken.action):
                return taken
            self.service.commanded(action)
        except StatusError as err:
            self.service.log.error(
                "operator command refused by the vehicle", command=taken.command, reason=err.message
            )
            done = operator.acted(taken, f"refused: {err.message}")
        else:
            done = operator.acted(taken, "accepted")
        self._save()
        return done

    def _save(self) -> None:
        store = self.service.store
        if store is not None:
            store.save_commanded(OPERATOR_KEY, self.service.core.operator.to_json())

    def restore(self) -> None:
        """Takes the operator's state back from the state file (a restarted drone is still
        paused, or the mission still ended)."""
        store = self.service.store
        kept = None if store is None else store.load_commanded().get(OPERATOR_KEY)
        if kept is None:
            return
        operator = self.service.core.operator = Operator.from_json(kept)
        if operator.paused is not None:
            self._unpaused = asyncio.Event()
            self.service.log.warning("still paused", reason=operator.paused.reason)
        if operator.ended is not None:
            self.service.log.warning("the mission has ended", reason=operator.ended.reason)


def command_proto(taken: OperatorCommand) -> drone_pb2.OperatorCommand:
    """An operator command as GetStatus, the replies and the report show it."""
    return drone_pb2.OperatorCommand(
        command=taken.command,
        at=taken.at,
        after_reqnr=taken.after_reqnr,
        action=taken.action,
        reason=taken.reason,
        by=taken.by,
        vehicle=taken.vehicle,
    )


def failsafe_proto(failsafe: Failsafe) -> drone_pb2.Failsafe:
    """The failsafe as GetStatus and Resume show it."""
    return drone_pb2.Failsafe(
        cause=failsafe.cause,
        action=failsafe.action,
        since=failsafe.since,
        reason=failsafe.reason,
        station=-1 if failsafe.station is None else failsafe.station,
    )


def fill_status(status: drone_pb2.DroneStatus, commands: OperatorCommands) -> None:
    """The operator's part of GetStatus: the pause, the end, every command."""
    operator = commands.service.core.operator
    if operator.paused is not None:
        status.paused.CopyFrom(command_proto(operator.paused))
    if operator.ended is not None:
        status.ended.CopyFrom(command_proto(operator.ended))
    status.operator_commands.extend(command_proto(c) for c in operator.commands)
