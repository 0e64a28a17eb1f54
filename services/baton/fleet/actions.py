"""The fleet's operations, one function each, for both ways in: the ``baton fleet``
commands (cli.py prints what these return) and the Fleet gRPC service (service.py
answers with it). Neither holds logic of its own beyond reading its input and
writing its output.

Each call opens the registry file for itself, as separate runs of the command do,
and blocks (SQLite, and the stations' and drones' gRPC, each question with its
deadline): the service runs them off its event loop. A failure is an exception
that says its kind, so that each way in says it its own way: RegistryError's
subclasses (an unknown mission, a name taken), RouteError (a submission's route),
ConfigError (a network file without a station the mission needs), SessionError
(a station that did not start or stop a session); a refused admission is a
``Refused`` returned, as admission decides it.

Admission that starts (``admit_and_start``): the mission is admitted (its row
written, so that a second submission for the drone is refused meanwhile), then
its sessions start on its whole ring or on none (sessions.py undoes a partial
start); a start that fails withdraws the row, so the mission was never
admitted. Only where the undo itself failed (a station that started the session
and then did not answer its stop) does the row stay, admitted, for a cancel to
finish.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from baton.config import BatonConfig, ConfigError, merge
from baton.drone.policy import Station
from baton.fleet.admission import Admitted, Refused
from baton.fleet.operations import (
    DrainReport,
    Overview,
    ask_drone,
    ask_stations,
    at_once,
    controller_status,
    drain,
    drone_of,
    overview,
    session_statuses,
)
from baton.fleet.registry import IN_FLIGHT, MissionRow, NotInFlight, Registry
from baton.fleet.sessions import SessionError, start_sessions, stop_sessions
from baton.fleet.stations import ring_config
from baton.rpc.tls import Tls
from baton.sdk.types import Position
from baton.v1 import drone_pb2, ring_pb2


@dataclass(frozen=True)
class Network:
    """The network's file, read (``source``: where from): its controllers are the
    stations at their addresses, its settings every mission's; and the operator's
    certificate the stations and drones are called with (None: insecure)."""

    config: BatonConfig
    source: str
    tls: Tls | None


@dataclass(frozen=True)
class Admission:
    """An admitted mission: its id, admission's decision, and the stations of the
    registry (by id) its ring names."""

    mission_id: int
    admitted: Admitted
    stations: dict[int, str]
    places: dict[int, Station]


def admit(registry: Path, drone: str, route: Sequence[Position]) -> Admission | Refused:
    """Admits ``drone``'s ``route`` over the registry's stations in service, or says why
    not (``Refused``)."""
    with Registry(registry) as open_registry:
        decision = open_registry.admit(drone, route)
        stations = open_registry.stations()
    if isinstance(decision, Refused):
        return decision
    mission_id, admitted = decision
    return Admission(
        mission_id,
        admitted,
        {s.station.id: s.name for s in stations},
        {s.station.id: s.station for s in stations},
    )


def mission_config(
    mission: MissionRow, network: Network, drone_address: str | None = None
) -> BatonConfig:
    """The configuration a mission's sessions and its drone run with: the network
    file's stations in its ring, admission's order and first master, its drone at
    ``drone_address`` (default: the file's) under its own identity where the
    operator's folder has one; ConfigError naming a ring station the file lacks,
    NotInFlight for a cancelled mission."""
    if mission.state != IN_FLIGHT:
        raise NotInFlight(f"mission {mission.id}: {mission.state}, not admitted")
    config = merge(
        network.config, [("--drone-address", "drone.address", drone_address)], network.source
    )
    missing = sorted(set(mission.ring) - {c.id for c in config.controllers})
    if missing:
        raise ConfigError(
            f"{network.source}: controllers: no station {', '.join(map(str, missing))} of "
            f"mission {mission.id}'s ring {list(mission.ring)}; add each with its id and address"
        )
    ringed = ring_config(config, mission.ring, mission.first_master)
    # The drone's own identity where the folder gives it one: its sessions take no other.
    drone = ringed.drone.model_copy(update={"name": drone_of(mission, network.tls).label})
    return ringed.model_copy(update={"drone": drone})


@dataclass(frozen=True)
class Started:
    """A mission whose sessions run on its ring, and the configuration they got (the
    drone's ring: its stations with their places and ranges, in order)."""

    mission: MissionRow
    config: BatonConfig


def start_mission(
    registry: Path,
    mission_id: int,
    network: Network,
    program: str,
    args: Sequence[str],
    drone_address: str | None = None,
) -> Started:
    """Starts an admitted mission's sessions on its ring's stations (a station drained
    out of it is not started again) and records its drone's address."""
    with Registry(registry) as open_registry:
        mission = open_registry.mission(mission_id)
    config = mission_config(mission, network, drone_address)
    start_sessions(config, str(mission.id), program, args, network.tls, mission.live_ring)
    with Registry(registry) as open_registry:
        open_registry.set_drone_address(mission.id, config.drone.address)
        mission = open_registry.mission(mission.id)
    return Started(mission, config)


def admit_and_start(
    registry: Path,
    drone: str,
    route: Sequence[Position],
    network: Network,
    program: str,
    args: Sequence[str],
    drone_address: str | None = None,
) -> tuple[Admission, Started] | Refused:
    """Admits the mission and starts its sessions (the module's docstring); the
    failure of the start, raised, after its admission was withdrawn."""
    admission = admit(registry, drone, route)
    if isinstance(admission, Refused):
        return admission
    try:
        started = start_mission(
            registry, admission.mission_id, network, program, args, drone_address
        )
    except SessionError as exc:
        mission_id = admission.mission_id
        if exc.leftover:
            raise SessionError(
                f"mission {mission_id}: {exc}; it stays admitted: cancel it (baton fleet "
                "cancel ID --config FILE) once the stations answer",
                exc.code,
                exc.leftover,
            ) from None
        _withdraw(registry, mission_id)
        raise SessionError(f"not admitted: {exc}", exc.code) from None
    except BaseException:
        _withdraw(registry, admission.mission_id)
        raise
    return admission, started


def _withdraw(registry: Path, mission_id: int) -> None:
    with Registry(registry) as open_registry:
        open_registry.withdraw(mission_id)


@dataclass(frozen=True)
class Cancelled:
    """A cancelled mission, and the stations its sessions were stopped on."""

    mission: MissionRow
    stopped_on: tuple[int, ...]


def cancel_mission(registry: Path, mission_id: int, network: Network | None) -> Cancelled:
    """Stops a mission's sessions on its ring's stations (with the network's file),
    then cancels it in the registry; SessionError naming the stations that did not
    stop theirs, the mission left admitted."""
    stopped: tuple[int, ...] = ()
    if network is not None:
        with Registry(registry) as open_registry:
            mission = open_registry.mission(mission_id)
        config = mission_config(mission, network)
        problems = stop_sessions(config, str(mission.id), network.tls)
        if problems:
            raise SessionError(
                f"mission {mission.id} not cancelled: its sessions did not all stop "
                f"({'; '.join(problems)}); cancel again once the stations answer"
            )
        stopped = mission.ring
    with Registry(registry) as open_registry:
        return Cancelled(open_registry.cancel(mission_id), stopped)


@dataclass(frozen=True)
class MissionLine:
    """A mission as ``missions`` lists it: its registry row, and for one in flight
    asked of its stations, what they say and which did not answer."""

    mission: MissionRow
    seen: Overview | None = None
    silent_stations: frozenset[int] = frozenset()


def mission_lines(registry: Path, network: Network | None) -> list[MissionLine]:
    """Every mission, by id; those in flight asked of their stations (all at once, each
    with its deadline) when ``network`` is given."""
    with Registry(registry) as open_registry:
        missions = open_registry.missions()
    if network is None:
        return [MissionLine(m) for m in missions]
    flying = [m for m in missions if m.state == IN_FLIGHT]
    replies = ask_stations(
        network.config, sorted({s for m in flying for s in m.live_ring}), network.tls
    )
    lines = []
    for m in missions:
        if m.state != IN_FLIGHT:
            lines.append(MissionLine(m))
            continue
        silent = frozenset(sid for sid in m.live_ring if isinstance(replies.get(sid), str))
        lines.append(MissionLine(m, overview(session_statuses(m, replies)), silent))
    return lines


@dataclass(frozen=True)
class MissionReport:
    """One mission's full status: its row, every session's status by station (or why
    none) and its drone's (or why none)."""

    mission: MissionRow
    sessions: dict[int, ring_pb2.ControllerStatus | str]
    drone: drone_pb2.DroneStatus | str


def mission_report(registry: Path, mission_id: int, network: Network) -> MissionReport:
    """Asks a mission's stations (its session's GetStatus) and its drone, at once."""
    with Registry(registry) as open_registry:
        mission = open_registry.mission(mission_id)
    known = {c.id for c in network.config.controllers}

    def ask(sid: int) -> ring_pb2.ControllerStatus | str:
        if sid not in known:
            return f"station {sid}: not in {network.source}; add it with its address"
        return controller_status(network.config, sid, mission.id, network.tls)

    sessions = at_once(ask, mission.live_ring)
    return MissionReport(mission, sessions, ask_drone(mission, network.tls))


def drain_station(registry: Path, station: str, network: Network) -> DrainReport:
    """Drains ``station`` (a name or an id) out of every ring that can do without it
    (operations.drain's steps)."""
    with Registry(registry) as open_registry:
        return drain(open_registry, station, network.config, network.tls)
