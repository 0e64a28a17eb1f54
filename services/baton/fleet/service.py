"""The Fleet gRPC service (protos/baton/v1/fleet.proto, ``baton fleet serve``): the
operations of ``baton fleet`` for a caller over gRPC.

Each method reads its request, runs the same function the command runs
(actions.py) off the event loop (they block on SQLite and on the stations'
and drones' gRPC), and writes its reply; nothing is decided here. Failures
are mapped once, by ``status_of`` and ``refusal_status``, to the status a
gRPC caller expects: INVALID_ARGUMENT for a request that can never succeed as
sent (naming the field), ALREADY_EXISTS for a station's name or id taken and a
drone with a mission in flight, FAILED_PRECONDITION for what could succeed in
another state (a route the stations do not cover yet, a cancelled mission, a
service without the network's file, a station that refused a session),
NOT_FOUND for an unknown mission or station, UNAVAILABLE for a station that
could not be reached.
"""

from __future__ import annotations

import asyncio
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import grpc

from baton.config import ConfigError, parse_address
from baton.drone.policy import Station
from baton.fleet.actions import (
    Admission,
    MissionLine,
    Network,
    Started,
    admit,
    admit_and_start,
    cancel_mission,
    drain_station,
    mission_lines,
    mission_report,
)
from baton.fleet.admission import Refusal, Refused
from baton.fleet.registry import (
    Malformed,
    MissionRow,
    NotInFlight,
    Registry,
    RegistryError,
    Taken,
    Unknown,
)
from baton.fleet.routes import RouteError, submitted_route
from baton.fleet.sessions import SessionError
from baton.lifecycle import announce, run_until_signalled
from baton.logs import get_logger
from baton.rpc.errors import StatusError, abort_with
from baton.rpc.ports import fleet_policy
from baton.rpc.server import BatonServer, servicer
from baton.rpc.tls import INSECURE_WARNING, Tls, TlsError
from baton.sdk.types import Position
from baton.v1 import fleet_pb2, fleet_pb2_grpc

SERVICE = "baton.v1.Fleet"
# A station's answer that means it was not reached, rather than that it refused.
_NOT_REACHED = (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED)
# The file a submitted plan's text is read from; a message naming it names the plan.
_PLAN_FILE = "submitted.plan"

T = TypeVar("T")

_REFUSAL_CODES = {
    Refusal.MALFORMED: grpc.StatusCode.INVALID_ARGUMENT,
    Refusal.BUSY: grpc.StatusCode.ALREADY_EXISTS,
    Refusal.UNCOVERED: grpc.StatusCode.FAILED_PRECONDITION,
    Refusal.NO_STATIONS: grpc.StatusCode.FAILED_PRECONDITION,
}


def refusal_status(refused: Refused) -> StatusError:
    """A refused admission as the caller sees it: the field and what is wrong."""
    return StatusError(_REFUSAL_CODES[refused.kind], f"refused: {refused.message()}")


def status_of(exc: Exception) -> StatusError | None:
    """The status of a failure of the fleet's operations (actions.py); None for one
    that is no request's fault (a bug: the caller sees UNKNOWN, the log has it)."""
    if isinstance(exc, StatusError):
        return exc
    code: grpc.StatusCode
    if isinstance(exc, Unknown):
        code = grpc.StatusCode.NOT_FOUND
    elif isinstance(exc, Taken):
        code = grpc.StatusCode.ALREADY_EXISTS
    elif isinstance(exc, Malformed | RouteError):
        code = grpc.StatusCode.INVALID_ARGUMENT
    elif isinstance(exc, NotInFlight | RegistryError | ConfigError | TlsError):
        code = grpc.StatusCode.FAILED_PRECONDITION
    elif isinstance(exc, SessionError):
        code = _session_code(exc.code)
    else:
        return None
    return StatusError(code, str(exc))


def _session_code(said: grpc.StatusCode) -> grpc.StatusCode:
    """A session that did not start or stop, by what its station answered: not reached
    is UNAVAILABLE; a field of the request it named (the program: no such file there)
    INVALID_ARGUMENT; any other refusal a state of that station's, FAILED_PRECONDITION."""
    if said in _NOT_REACHED:
        return grpc.StatusCode.UNAVAILABLE
    if said == grpc.StatusCode.INVALID_ARGUMENT:
        return said
    return grpc.StatusCode.FAILED_PRECONDITION


def invalid(field: str, why: str) -> StatusError:
    return StatusError(grpc.StatusCode.INVALID_ARGUMENT, f"{field}: {why}")


def _position(place: fleet_pb2.Place) -> Position:
    return Position(place.latitude_deg, place.longitude_deg)


def _place(position: Position) -> fleet_pb2.Place:
    return fleet_pb2.Place(latitude_deg=position.latitude_deg, longitude_deg=position.longitude_deg)


def submitted(request: fleet_pb2.AdmitRequest) -> list[Position]:
    """The route an Admit gives: its points, or its plan's text read as a plan file;
    RouteError naming the field."""
    points = [_position(p) for p in request.route]
    home = _position(request.home) if request.HasField("home") else None
    if not request.plan:
        return submitted_route(points, None, home)
    with tempfile.TemporaryDirectory(prefix="baton-plan-") as folder:
        path = Path(folder) / _PLAN_FILE
        path.write_text(request.plan)
        try:
            return submitted_route(points, path, home)
        except RouteError as exc:
            sent = exc.reason.replace(f"plan {path}", "the plan sent").replace(
                str(path), "the plan sent"
            )
            raise RouteError(exc.field, sent) from None


def summary(line: MissionLine) -> fleet_pb2.MissionSummary:
    """A mission's row, and what its stations said of it where they were asked."""
    m = line.mission
    reply = _row(m)
    if line.seen is not None:
        reply.asked = True
        if line.seen.master is not None:
            reply.master = line.seen.master
        reply.program_state = line.seen.state
        reply.reqnr = line.seen.reqnr
        reply.silent.extend(line.seen.silent)
    return reply


def _row(m: MissionRow) -> fleet_pb2.MissionSummary:
    return fleet_pb2.MissionSummary(
        id=m.id,
        drone=m.drone,
        state=m.state,
        ring=list(m.live_ring),
        first_master=m.first_master,
        admitted_at_unix_s=m.admitted_at,
        drone_address=m.drone_address or "",
    )


def admit_reply(admission: Admission, started: Started | None) -> fleet_pb2.AdmitReply:
    admitted = admission.admitted
    reply = fleet_pb2.AdmitReply(
        mission_id=admission.mission_id,
        first_master=admitted.first_master,
        length_m=admitted.length_m,
        started=started is not None,
    )
    for sid in admitted.ring:
        station = admission.places[sid]
        reply.ring.add(
            id=sid,
            name=admission.stations[sid],
            location=_place(station.location),
            range_m=station.range_m,
            enters_at_m=admitted.enters_at_m[sid],
        )
    if started is not None:
        reply.mission_config = started.config.model_dump_json(exclude_unset=True)
    return reply


class FleetService(fleet_pb2_grpc.FleetServicer):
    """The Fleet service over the registry file ``registry`` and, where given, the
    network's file (the stations' addresses, the operator's certificate)."""

    def __init__(self, registry: Path, network: Network | None) -> None:
        self.registry = registry
        self.network = network
        self.log = get_logger("fleet")

    def _needs_network(self, what: str) -> Network:
        if self.network is None:
            raise StatusError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"{what}: this fleet service has no network file (the stations' addresses); "
                "restart it with baton fleet serve --config NETWORK.yaml",
            )
        return self.network

    async def _run(self, context: grpc.aio.ServicerContext, work: Callable[[], T]) -> T:
        """``work()`` off the event loop; its failure ended with its status."""
        try:
            return await asyncio.to_thread(work)
        except Exception as exc:
            error = status_of(exc)
            if error is None:
                raise
            self.log.info("refused", reason=error.message, code=error.code.name)
            await abort_with(context, error)

    async def AddStation(
        self, request: fleet_pb2.AddStationRequest, context: grpc.aio.ServicerContext
    ) -> fleet_pb2.FleetStation:
        def add() -> fleet_pb2.FleetStation:
            if not request.HasField("location"):
                raise invalid("location", "missing: the station's antenna, degrees")
            station = Station(request.id, _position(request.location), request.range_m)
            with Registry(self.registry) as registry:
                registry.add_station(request.name, station)
                added = registry.station(request.name)
            return _station(added.name, added.station, added.drained)

        return await self._run(context, add)

    async def ListStations(
        self, request: fleet_pb2.ListStationsRequest, context: grpc.aio.ServicerContext
    ) -> fleet_pb2.ListStationsReply:
        def stations() -> fleet_pb2.ListStationsReply:
            with Registry(self.registry) as registry:
                found = registry.stations()
            return fleet_pb2.ListStationsReply(
                stations=[_station(s.name, s.station, s.drained) for s in found]
            )

        return await self._run(context, stations)

    async def Admit(
        self, request: fleet_pb2.AdmitRequest, context: grpc.aio.ServicerContext
    ) -> fleet_pb2.AdmitReply:
        def run() -> fleet_pb2.AdmitReply:
            route = submitted(request)
            if not request.start:
                for field, given in (
                    ("program", request.program),
                    ("args", request.args),
                    ("drone_address", request.drone_address),
                ):
                    if given:
                        raise invalid(field, "only with start")
                admission = admit(self.registry, request.drone, route)
                if isinstance(admission, Refused):
                    raise refusal_status(admission)
                return admit_reply(admission, None)
            if not request.program:
                raise invalid("program", "missing: start needs the mission program's path")
            if request.drone_address:
                try:
                    parse_address(request.drone_address)
                except ValueError as exc:
                    raise invalid("drone_address", str(exc)) from None
            network = self._needs_network("start")
            both = admit_and_start(
                self.registry,
                request.drone,
                route,
                network,
                request.program,
                list(request.args),
                request.drone_address or None,
            )
            if isinstance(both, Refused):
                raise refusal_status(both)
            return admit_reply(*both)

        return await self._run(context, run)

    async def ListMissions(
        self, request: fleet_pb2.ListMissionsRequest, context: grpc.aio.ServicerContext
    ) -> fleet_pb2.ListMissionsReply:
        network = None if request.registry_only else self.network

        def missions() -> fleet_pb2.ListMissionsReply:
            lines = mission_lines(self.registry, network)
            return fleet_pb2.ListMissionsReply(missions=[summary(line) for line in lines])

        return await self._run(context, missions)

    async def GetMission(
        self, request: fleet_pb2.GetMissionRequest, context: grpc.aio.ServicerContext
    ) -> fleet_pb2.MissionStatus:
        def status() -> fleet_pb2.MissionStatus:
            network = self._needs_network("GetMission")
            report = mission_report(self.registry, request.mission_id, network)
            reply = fleet_pb2.MissionStatus(
                mission=_row(report.mission), departed=list(report.mission.departed)
            )
            for sid, session in report.sessions.items():
                if isinstance(session, str):
                    reply.sessions[sid].error = session
                else:
                    reply.sessions[sid].status.CopyFrom(session)
            if isinstance(report.drone, str):
                reply.drone_error = report.drone
            else:
                reply.drone_status.CopyFrom(report.drone)
            return reply

        return await self._run(context, status)

    async def CancelMission(
        self, request: fleet_pb2.CancelMissionRequest, context: grpc.aio.ServicerContext
    ) -> fleet_pb2.CancelMissionReply:
        def cancel() -> fleet_pb2.CancelMissionReply:
            cancelled = cancel_mission(self.registry, request.mission_id, self.network)
            return fleet_pb2.CancelMissionReply(
                mission=_row(cancelled.mission), stopped_on=list(cancelled.stopped_on)
            )

        return await self._run(context, cancel)

    async def DrainStation(
        self, request: fleet_pb2.DrainStationRequest, context: grpc.aio.ServicerContext
    ) -> fleet_pb2.DrainReply:
        def run() -> fleet_pb2.DrainReply:
            if not request.station:
                raise invalid("station", "missing: the station's name or id")
            network = self._needs_network("DrainStation")
            report = drain_station(self.registry, request.station, network)
            reply = fleet_pb2.DrainReply(
                station=report.station, failed=report.failed, done=report.done
            )
            for mission_id, target in report.left:
                left = reply.left.add(mission_id=mission_id)
                if target is not None:
                    left.master_to = target
            for stay in report.stayed:
                reply.stayed.add(mission_id=stay.mission_id, reason=stay.reason)
            return reply

        return await self._run(context, run)


def _station(name: str, station: Station, drained: bool) -> fleet_pb2.FleetStation:
    return fleet_pb2.FleetStation(
        name=name,
        id=station.id,
        location=_place(station.location),
        range_m=station.range_m,
        drained=drained,
    )


def fleet_server(
    registry: Path, network: Network | None, tls: Tls | None, listen: str
) -> BatonServer:
    """The Fleet service's server on ``listen`` (not started), as the operator."""
    service = FleetService(registry, network)
    if tls is None:
        service.log.warning(INSECURE_WARNING)
    return BatonServer(
        listen,
        [servicer(SERVICE, fleet_pb2_grpc.add_FleetServicer_to_server, service)],
        tls=tls,
        policy=fleet_policy(),
    )


async def serve_fleet(
    registry: Path,
    network: Network | None,
    tls: Tls | None,
    listen: str,
    address_file: str | None,
) -> int:
    """Serves the Fleet service until SIGTERM or SIGINT."""

    async def main(stop: asyncio.Event) -> int:
        server = fleet_server(registry, network, tls, listen)
        await server.start()
        announce(
            address_file,
            [server.address],
            {"fleet": str(registry), "address": server.address},
        )
        await stop.wait()
        await server.stop()
        return 0

    return await run_until_signalled(main)
