"""``baton fleet``: the registry of stations and admitted missions (issue 34, item 2),
and an admitted mission's sessions on its stations (item 1).

    baton fleet stations add NAME --id N --at LAT,LON --range M
    baton fleet stations add --from-config examples/corridor.yaml
    baton fleet stations list
    baton fleet admit --drone D --plan FILE [--home LAT,LON] | --route LAT,LON LAT,LON ...
    baton fleet missions [--config FILE]
    baton fleet status ID --config FILE
    baton fleet start ID --config FILE --mission FILE [--mission-arg k=v ...]
    baton fleet cancel ID [--config FILE]
    baton fleet drain STATION --config FILE
    baton fleet undrain STATION
    baton fleet view --config FILE [--listen HOST:PORT]

Exit status: 0 done, 1 a mission refused (or a drain that left the station in
some ring: the report says why), 2 a request that cannot be done (the
message names the flag or field and the fix).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from baton.certs.cli import add_tls_flags, tls_from_flags
from baton.sdk.run import add_mission_arg

if TYPE_CHECKING:
    from baton.config import BatonConfig
    from baton.fleet.registry import MissionRow
    from baton.rpc.tls import Tls
    from baton.sdk.types import Position
    from baton.v1.ring_pb2 import ControllerStatus

DEFAULT_REGISTRY = Path("baton-fleet.sqlite")
# A station's fields (admission.station_problem) and the flags that set them.
STATION_FLAGS = {"id": "--id", "location": "--at", "range_m": "--range"}


def _place(text: str) -> tuple[float, float]:
    """``LAT,LON`` in degrees, as typed (bounds are admission's to check)."""
    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        return float(parts[0]), float(parts[1])
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected LAT,LON in degrees, e.g. 47.397742,8.545594"
        ) from None


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Adds ``baton fleet stations add|list``, ``admit``, ``missions`` and ``cancel``."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--registry",
        type=Path,
        default=DEFAULT_REGISTRY,
        metavar="FILE",
        help=f"the registry's SQLite file, made if absent (default ./{DEFAULT_REGISTRY})",
    )
    parser = subparsers.add_parser(
        "fleet",
        help="stations and mission admission: which stations cover a route, the ring",
        description=(
            "The registry of stations (position, radio range) and admitted missions, in one "
            "SQLite file. 'admit' decides which stations cover a drone's route: the ring is "
            "the covering stations in route order, the first master the nearest to take-off; "
            "a route with a stretch no station covers is refused, naming it. 'start' starts an "
            "admitted mission's sessions on its ring's stations (baton station), 'cancel "
            "--config' stops them. 'missions --config' and 'status' ask the stations and "
            "drones; 'drain' takes a station out of every ring that can do without it."
        ),
    )
    actions = parser.add_subparsers(dest="fleet_action", metavar="ACTION", required=True)

    stations = actions.add_parser("stations", help="add or list stations")
    station_actions = stations.add_subparsers(
        dest="stations_action", metavar="ACTION", required=True
    )
    add = station_actions.add_parser(
        "add", parents=[common], help="register a station, or a testbed file's controllers"
    )
    add.add_argument("name", nargs="?", help="the station's name (unique)")
    add.add_argument("--id", type=int, help="its controller id in rings (unique, >= 0)")
    add.add_argument("--at", type=_place, metavar="LAT,LON", help="its antenna, degrees")
    add.add_argument("--range", type=float, metavar="M", help="its radio range, metres")
    add.add_argument(
        "--from-config",
        type=Path,
        metavar="FILE",
        help="register every controller of a testbed file (location, range_m) as "
        "station controller-ID instead",
    )
    add.set_defaults(run=_guarded(_add_stations))
    station_actions.add_parser("list", parents=[common], help="the stations").set_defaults(
        run=_guarded(_list_stations)
    )

    admit = actions.add_parser(
        "admit", parents=[common], help="admit a drone's mission: its ring and first master"
    )
    admit.add_argument("--drone", required=True, help="the drone's name")
    route = admit.add_mutually_exclusive_group(required=True)
    route.add_argument(
        "--plan", type=Path, metavar="FILE", help="a QGroundControl plan (.plan or QGC WPL)"
    )
    route.add_argument(
        "--route",
        type=_place,
        nargs="+",
        metavar="LAT,LON",
        help="the route: take-off first, then each position flown to",
    )
    admit.add_argument(
        "--home",
        type=_place,
        metavar="LAT,LON",
        help="(--plan) the take-off point (default: the plan's planned home position)",
    )
    admit.set_defaults(run=_guarded(_admit))

    network = argparse.ArgumentParser(add_help=False)
    network.add_argument(
        "--config",
        type=Path,
        metavar="FILE",
        help="the network's testbed file: its controllers are the stations at their ports "
        "(id, address), its drone the mission's (or --drone-address)",
    )
    add_tls_flags(network)
    actions.add_parser(
        "missions",
        parents=[common, network],
        help="the admitted missions; with --config, each one's master, state and progress "
        "as its stations say",
    ).set_defaults(run=_guarded(_missions))

    def on_mission(
        name: str, what: str, run: Callable[[argparse.Namespace], int]
    ) -> argparse.ArgumentParser:
        """An action on one mission, by its id, with the network's file."""
        action = actions.add_parser(name, parents=[common, network], help=what)
        action.add_argument("mission", type=int, help="the mission's id (baton fleet missions)")
        action.set_defaults(run=_guarded(run))
        return action

    on_mission(
        "status",
        "one mission's full status: every session's ControllerStatus and the drone's, as JSON",
        _status,
    )
    drain = actions.add_parser(
        "drain",
        parents=[common, network],
        help="take a station out of service: in no new ring, its masters handed over, and "
        "out of every ring that can do without it",
    )
    drain.add_argument("station", help="the station's name or id (baton fleet stations list)")
    drain.set_defaults(run=_guarded(_drain))
    undrain = actions.add_parser(
        "undrain", parents=[common], help="admit a drained station into new rings again"
    )
    undrain.add_argument("station", help="the station's name or id")
    undrain.set_defaults(run=_guarded(_undrain))
    start = on_mission(
        "start",
        "start an admitted mission's sessions on its ring's stations (baton station)",
        _start,
    )
    start.add_argument(
        "--mission",
        dest="program",
        required=True,
        metavar="FILE",
        help="the mission program, a path on the stations",
    )
    add_mission_arg(start)
    start.add_argument(
        "--drone-address",
        metavar="HOST:PORT",
        help="where the stations reach the mission's drone (default: the file's drone.address)",
    )
    view = actions.add_parser(
        "view",
        parents=[common, network],
        help="a live web page of the stations, their ranges and the drones moving, with "
        "each mission's master and state",
    )
    view.add_argument(
        "--listen",
        default="127.0.0.1:8470",
        metavar="HOST:PORT",
        help="where the page is served; port 0 picks a free one (default 127.0.0.1:8470)",
    )
    view.add_argument("--address-file", help="write the bound HOST:PORT to this file")
    view.add_argument(
        "--poll",
        type=float,
        default=0.5,
        metavar="S",
        help="how often the stations and drones are asked, seconds (default 0.5)",
    )
    view.set_defaults(run=_guarded(_view))
    on_mission(
        "cancel",
        "cancel an admitted mission; with --config, its sessions stopped on its stations",
        _cancel,
    )


def _guarded(action: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """``action`` with a registry that cannot be used said as a clear error."""

    def run(args: argparse.Namespace) -> int:
        from baton.fleet.registry import RegistryError

        try:
            return action(args)
        except RegistryError as exc:
            return _fail(args, str(exc))

    return run


def _fail(args: argparse.Namespace, message: str, status: int = 2) -> int:
    action = (
        args.fleet_action if args.fleet_action != "stations" else "stations " + args.stations_action
    )
    print(f"baton fleet {action}: {message}", file=sys.stderr)
    return status


def _add_stations(args: argparse.Namespace) -> int:
    from baton.config import ConfigError, load_config
    from baton.drone.policy import Station
    from baton.fleet.admission import station_problem
    from baton.fleet.registry import Registry, RegistryError
    from baton.fleet.stations import stations_of
    from baton.sdk.types import Position

    flags = {"NAME": args.name, "--id": args.id, "--at": args.at, "--range": args.range}
    if args.from_config is not None:
        given = [flag for flag, value in flags.items() if value is not None]
        if given:
            return _fail(args, f"{', '.join(given)}: not with --from-config; give one or the other")
        try:
            config = load_config(args.from_config)
            named = [(f"controller-{s.id}", s) for s in stations_of(config, str(args.from_config))]
        except ConfigError as exc:
            return _fail(args, str(exc))
    else:
        missing = [flag for flag, value in flags.items() if value is None]
        if missing:
            return _fail(
                args, f"{', '.join(missing)}: missing; e.g. s0 --id 0 --at 47.398,8.546 --range 500"
            )
        station = Station(args.id, Position(*args.at), args.range)
        problem = station_problem(station)
        if problem is not None:
            field, why = problem
            return _fail(args, f"{STATION_FLAGS[field.partition('.')[0]]} {why}")
        named = [(args.name, station)]
    with Registry(args.registry) as registry:
        for name, station in named:
            try:
                registry.add_station(name, station)
            except RegistryError as exc:
                return _fail(args, f"station {name}: {exc}")
            print(f"station {name} (id {station.id}) added")
    return 0


def _list_stations(args: argparse.Namespace) -> int:
    from baton.fleet.registry import Registry

    with Registry(args.registry) as registry:
        stations = registry.stations()
    print(f"{'ID':>4}  {'NAME':<16} {'LATITUDE':>11} {'LONGITUDE':>11} {'RANGE_M':>8}  STATE")
    for s in stations:
        where = s.station.location
        print(
            f"{s.station.id:>4}  {s.name:<16} {where.latitude_deg:>11.6f} "
            f"{where.longitude_deg:>11.6f} {s.station.range_m:>8g}  "
            f"{'drained' if s.drained else 'in service'}"
        )
    return 0


def _route(args: argparse.Namespace) -> list[Position]:
    """The submitted route: --route's points, or the plan's from its take-off point;
    ValueError names the flag and the fix."""
    from baton.fleet.routes import plan_route, planned_home
    from baton.missions.plan import PlanError, load_plan
    from baton.sdk.types import Position

    if args.route is not None:
        if args.home is not None:
            raise ValueError("--home: for --plan; --route's first point is the take-off")
        return [Position(lat, lon) for lat, lon in args.route]
    try:
        plan = load_plan(str(args.plan))
        home = Position(*args.home) if args.home is not None else planned_home(args.plan)
    except PlanError as exc:
        raise ValueError(f"--plan: {exc}") from None
    if home is None:
        raise ValueError(
            f"--plan {args.plan}: the plan has no planned home position; give the take-off "
            "point with --home LAT,LON"
        )
    return plan_route(plan, home)


def _admit(args: argparse.Namespace) -> int:
    from baton.fleet.admission import Refused
    from baton.fleet.registry import Registry

    try:
        route = _route(args)
    except ValueError as exc:
        return _fail(args, str(exc))
    with Registry(args.registry) as registry:
        decision = registry.admit(args.drone, route)
        names = {s.station.id: s.name for s in registry.stations()}
    if isinstance(decision, Refused):
        return _fail(args, f"refused: {decision.message()}", status=1)
    mission_id, admitted = decision
    print(
        f"mission {mission_id} admitted for drone {args.drone}: a {admitted.length_m:.0f} m route"
    )
    ring = " -> ".join(
        f"{names[sid]} (id {sid}, from {admitted.enters_at_m[sid]:.0f} m)" for sid in admitted.ring
    )
    print(f"ring: {ring}")
    first = admitted.first_master
    print(f"first master: {names[first]} (id {first}), the nearest to take-off")
    return 0


def _missions(args: argparse.Namespace) -> int:
    from baton.config import ConfigError, load_config
    from baton.fleet.operations import ask_stations, overview, session_statuses
    from baton.fleet.registry import IN_FLIGHT, Registry
    from baton.rpc.tls import OPERATOR, TlsError

    with Registry(args.registry) as registry:
        missions = registry.missions()
    if args.config is None:
        print(f"{'ID':>4}  {'DRONE':<12} {'STATE':<10} {'FIRST':>6}  {'ADMITTED (UTC)':<20} RING")
        for m in missions:
            admitted_at = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(m.admitted_at))
            ring = ",".join(map(str, m.live_ring))
            print(
                f"{m.id:>4}  {m.drone:<12} {m.state:<10} {m.first_master:>6}  "
                f"{admitted_at:<20} {ring}"
            )
        return 0
    try:
        network = load_config(args.config)
        tls = tls_from_flags(args, network, OPERATOR)
    except (ConfigError, TlsError) as exc:
        return _fail(args, str(exc))
    flying = [m for m in missions if m.state == IN_FLIGHT]
    replies = ask_stations(network, sorted({s for m in flying for s in m.live_ring}), tls)
    print(f"{'ID':>4}  {'DRONE':<12} {'STATE':<10} {'MASTER':>6} {'REQNR':>6}  RING")
    silent: set[str] = set()
    for m in missions:
        if m.state != IN_FLIGHT:
            ring = ",".join(map(str, m.live_ring))
            print(f"{m.id:>4}  {m.drone:<12} {m.state:<10} {'-':>6} {'-':>6}  {ring}")
            continue
        seen = overview(session_statuses(m, replies))
        silent.update(seen.silent)
        # A station whose session did not answer is marked with '?'.
        ring = ",".join(
            f"{sid}{'?' if isinstance(replies.get(sid), str) else ''}" for sid in m.live_ring
        )
        master = "?" if seen.master is None else str(seen.master)
        print(f"{m.id:>4}  {m.drone:<12} {seen.state:<10} {master:>6} {seen.reqnr:>6}  {ring}")
    for line in sorted(silent):
        print(f"  {line}")
    return 0


def _status(args: argparse.Namespace) -> int:
    import json

    from google.protobuf.json_format import MessageToDict

    from baton.config import ConfigError, load_config
    from baton.fleet.operations import ask_drone, at_once, controller_status
    from baton.fleet.registry import Registry
    from baton.rpc.tls import OPERATOR, TlsError

    if args.config is None:
        return _fail(args, "--config: missing; the network's file with the stations' addresses")
    with Registry(args.registry) as registry:
        mission = registry.mission(args.mission)
    try:
        network = load_config(args.config)
        tls = tls_from_flags(args, network, OPERATOR)
    except (ConfigError, TlsError) as exc:
        return _fail(args, str(exc))
    known = {c.id for c in network.controllers}

    def ask(sid: int) -> ControllerStatus | str:
        if sid not in known:
            return f"station {sid}: not in {args.config}; add it with its address"
        return controller_status(network, sid, mission.id, tls)

    sessions = at_once(ask, mission.live_ring)
    drone = ask_drone(mission, tls)
    document = {
        "mission": mission.id,
        "drone": mission.drone,
        "state": mission.state,
        "ring": list(mission.live_ring),
        "departed": list(mission.departed),
        "first_master": mission.first_master,
        "sessions": {
            str(sid): {"error": s} if isinstance(s, str) else MessageToDict(s)
            for sid, s in sessions.items()
        },
        "drone_status": {"error": drone} if isinstance(drone, str) else MessageToDict(drone),
    }
    print(json.dumps(document, indent=2))
    return 0


def _drain(args: argparse.Namespace) -> int:
    from baton.config import ConfigError, load_config
    from baton.fleet.operations import drain
    from baton.fleet.registry import Registry
    from baton.rpc.tls import OPERATOR, TlsError

    if args.config is None:
        return _fail(args, "--config: missing; the network's file with the stations' addresses")
    try:
        network = load_config(args.config)
        tls = tls_from_flags(args, network, OPERATOR)
    except (ConfigError, TlsError) as exc:
        return _fail(args, str(exc))
    with Registry(args.registry) as registry:
        report = drain(registry, args.station, network, tls)
    print(f"station {report.station} drained: admitted into no new ring")
    for mission, target in report.left:
        moved = f", its master handed over to station {target}" if target is not None else ""
        print(f"mission {mission}: left its ring{moved}")
    for stay in report.stayed:
        print(f"mission {stay.mission_id}: stays in its ring: {stay.reason}")
    for problem in report.failed:
        print(f"{problem}")
    if not report.done:
        return _fail(
            args,
            f"station {report.station} still serves "
            f"{len(report.stayed) + len(report.failed)} mission(s) (above); run drain again "
            "later, or cancel them",
            status=1,
        )
    return 0


def _undrain(args: argparse.Namespace) -> int:
    from baton.fleet.registry import Registry

    with Registry(args.registry) as registry:
        station = registry.set_drained(args.station, False)
    print(f"station {station.name} (id {station.station.id}) admitted into new rings again")
    return 0


def _mission_network(args: argparse.Namespace) -> tuple[MissionRow, BatonConfig, Tls | None]:
    """The admitted mission, the configuration its ring's sessions run with (the
    network file's stations in the ring, admission's order and first master), and the
    operator's certificate; ConfigError, TlsError or RegistryError saying why not."""
    from baton.config import ConfigError, load_config, merge
    from baton.fleet.operations import drone_of
    from baton.fleet.registry import IN_FLIGHT, Registry, RegistryError
    from baton.fleet.stations import ring_config
    from baton.rpc.tls import OPERATOR

    with Registry(args.registry) as registry:
        mission = registry.mission(args.mission)
    if mission.state != IN_FLIGHT:
        raise RegistryError(f"mission {mission.id}: {mission.state}, not admitted")
    network = load_config(args.config)
    address = getattr(args, "drone_address", None)
    network = merge(network, [("--drone-address", "drone.address", address)], str(args.config))
    missing = sorted(set(mission.ring) - {c.id for c in network.controllers})
    if missing:
        raise ConfigError(
            f"{args.config}: controllers: no station {', '.join(map(str, missing))} of mission "
            f"{mission.id}'s ring {list(mission.ring)}; add each with its id and address"
        )
    config = ring_config(network, mission.ring, mission.first_master)
    tls = tls_from_flags(args, network, OPERATOR)
    # The drone's own identity where the folder gives it one: its sessions take no other.
    drone = config.drone.model_copy(update={"name": drone_of(mission, tls).label})
    return mission, config.model_copy(update={"drone": drone}), tls


def _start(args: argparse.Namespace) -> int:
    from baton.config import ConfigError
    from baton.fleet.registry import Registry
    from baton.fleet.sessions import SessionError, start_sessions
    from baton.rpc.tls import TlsError

    if args.config is None:
        return _fail(args, "--config: missing; the network's file with the stations' addresses")
    try:
        mission, config, tls = _mission_network(args)
        # A station drained out of the ring is not started again.
        start_sessions(
            config, str(mission.id), args.program, args.mission_arg, tls, mission.live_ring
        )
    except (ConfigError, TlsError) as exc:
        return _fail(args, str(exc))
    except SessionError as exc:
        return _fail(args, f"mission {args.mission}: {exc}", status=1)
    with Registry(args.registry) as registry:
        registry.set_drone_address(mission.id, config.drone.address)
    ring = ", ".join(
        f"{sid}{' (first master)' if sid == mission.first_master else ''}"
        for sid in mission.live_ring
    )
    print(f"mission {mission.id} of drone {mission.drone} started on stations {ring}")
    return 0


def _cancel(args: argparse.Namespace) -> int:
    from baton.config import ConfigError
    from baton.fleet.registry import Registry
    from baton.fleet.sessions import stop_sessions
    from baton.rpc.tls import TlsError

    if args.config is not None:
        try:
            mission, config, tls = _mission_network(args)
        except (ConfigError, TlsError) as exc:
            return _fail(args, str(exc))
        problems = stop_sessions(config, str(mission.id), tls)
        if problems:
            return _fail(
                args,
                f"mission {mission.id} not cancelled: its sessions did not all stop "
                f"({'; '.join(problems)}); run cancel again once the stations answer",
            )
        print(f"mission {mission.id}: sessions stopped on stations {list(mission.ring)}")
    with Registry(args.registry) as registry:
        cancelled = registry.cancel(args.mission)
    print(f"mission {cancelled.id} of drone {cancelled.drone} cancelled")
    return 0


def _view(args: argparse.Namespace) -> int:
    from functools import partial

    from baton import lifecycle
    from baton.config import ConfigError, load_config
    from baton.rpc.tls import OPERATOR, TlsError
    from baton.view.network import read_network
    from baton.view.server import serve_view

    if args.config is None:
        return _fail(args, "--config: missing; the network's file with the stations' addresses")
    host, _, port = args.listen.rpartition(":")
    if not host or not port.isdigit() or int(port) > 65_535:
        return _fail(args, f"--listen {args.listen!r}: expected HOST:PORT, e.g. 127.0.0.1:8470")
    if not args.poll > 0:
        return _fail(args, f"--poll {args.poll}: a number of seconds above 0, e.g. 0.5")
    if not args.registry.is_file():
        return _fail(
            args,
            f"--registry {args.registry}: no such file; give the registry the missions were "
            "admitted in (baton fleet admit)",
        )
    try:
        network = load_config(args.config)
        tls = tls_from_flags(args, network, OPERATOR)
    except (ConfigError, TlsError) as exc:
        return _fail(args, str(exc))
    read = partial(read_network, args.registry, network, tls)
    return lifecycle.run(serve_view(read, args.listen, args.poll, args.address_file))
