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
    baton fleet admit ... --start --config FILE --mission FILE [--drone-config FILE]
    baton fleet serve [--config FILE] [--listen HOST:PORT]
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
    from baton.fleet.actions import Admission, Network, Started
    from baton.fleet.admission import Refused
    from baton.sdk.types import Position

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

    network = argparse.ArgumentParser(add_help=False)
    network.add_argument(
        "--config",
        type=Path,
        metavar="FILE",
        help="the network's testbed file: its controllers are the stations at their ports "
        "(id, address), its drone the mission's (or --drone-address)",
    )
    add_tls_flags(network)

    admit = actions.add_parser(
        "admit",
        parents=[common, network],
        help="admit a drone's mission: its ring and first master; with --start, its "
        "sessions started on the ring's stations too",
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
    admit.add_argument(
        "--start",
        action="store_true",
        help="start the mission's sessions on its ring's stations too (needs --config and "
        "--mission); a start that fails leaves the mission not admitted",
    )
    _add_start_flags(admit, required=False)
    admit.set_defaults(run=_guarded(_admit))

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
    _add_start_flags(start, required=True)
    view = actions.add_parser(
        "view",
        parents=[common, network],
        help="a live web page of the stations, their ranges and the drones moving, with "
        "each mission's master and state",
    )
    _add_listen(view, "127.0.0.1:8470", "the page is served")
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
    serve = actions.add_parser(
        "serve",
        parents=[common, network],
        help="serve these operations over gRPC (the Fleet service) for the operator",
        description=(
            "Serves the Fleet gRPC service (protos/baton/v1/fleet.proto) over the registry: "
            "stations, admission (and start), missions, status, cancel and drain, by the same "
            "code as these commands. Only the operator's certificate may call it, and it "
            "presents that certificate (call it with -servername operator.baton). With "
            "--config (the network's file) it reaches the stations and drones; without, "
            "the calls that need them are refused FAILED_PRECONDITION."
        ),
    )
    _add_listen(serve, "127.0.0.1:50090", "the service listens")
    serve.set_defaults(run=_guarded(_serve))


def _add_listen(parser: argparse.ArgumentParser, default: str, what: str) -> None:
    """``--listen`` (checked by ``_listen_problem``) and ``--address-file``."""
    parser.add_argument(
        "--listen",
        default=default,
        metavar="HOST:PORT",
        help=f"where {what}; port 0 picks a free one (default {default})",
    )
    parser.add_argument("--address-file", help="write the bound HOST:PORT to this file")


def _listen_problem(listen: str) -> str | None:
    """What is wrong with a ``--listen`` value, or None."""
    from baton.config import parse_address

    try:
        parse_address(listen)
    except ValueError as exc:
        return f"--listen {listen!r}: {exc}"
    return None


def _add_start_flags(parser: argparse.ArgumentParser, required: bool) -> None:
    """What starting a mission's sessions takes: its program and arguments, where its
    drone is, and where to write the configuration its drone takes its ring from."""
    parser.add_argument(
        "--mission",
        dest="program",
        required=required,
        metavar="FILE",
        help="the mission program, a path on the stations",
    )
    add_mission_arg(parser)
    parser.add_argument(
        "--drone-address",
        metavar="HOST:PORT",
        help="where the stations reach the mission's drone (default: the file's drone.address)",
    )
    parser.add_argument(
        "--drone-config",
        type=Path,
        metavar="FILE",
        help="write the mission's configuration here (JSON): its ring's stations with their "
        "addresses, locations and ranges, in order; the drone's baton drone --config",
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
    RouteError names the field (its flag)."""
    from baton.fleet.routes import submitted_route
    from baton.sdk.types import Position

    points = [Position(lat, lon) for lat, lon in args.route or ()]
    home = Position(*args.home) if args.home is not None else None
    return submitted_route(points, args.plan, home)


def _network(args: argparse.Namespace) -> Network:
    """The network's file (--config) and the operator's certificate; ConfigError or
    TlsError saying why not."""
    from baton.config import load_config
    from baton.fleet.actions import Network
    from baton.rpc.tls import OPERATOR

    config = load_config(args.config)
    return Network(config, str(args.config), tls_from_flags(args, config, OPERATOR))


def _admit(args: argparse.Namespace) -> int:
    from baton.config import ConfigError
    from baton.fleet.actions import admit, admit_and_start
    from baton.fleet.admission import Refused
    from baton.fleet.routes import RouteError
    from baton.fleet.sessions import SessionError
    from baton.rpc.tls import TlsError

    try:
        route = _route(args)
    except RouteError as exc:
        return _fail(args, f"--{exc.field}: {exc.reason}")
    started: Started | None = None
    if not args.start:
        for flag, given in (
            ("--mission", args.program),
            ("--config", args.config),
            ("--mission-arg", args.mission_arg),
            ("--drone-address", args.drone_address),
            ("--drone-config", args.drone_config),
        ):
            if given:
                return _fail(args, f"{flag}: only with --start")
        decision: Admission | Refused = admit(args.registry, args.drone, route)
    else:
        if args.config is None or args.program is None:
            missing = "--config" if args.config is None else "--mission"
            return _fail(args, f"{missing}: missing; --start needs --config and --mission")
        try:
            both = admit_and_start(
                args.registry,
                args.drone,
                route,
                _network(args),
                args.program,
                args.mission_arg,
                args.drone_address,
            )
        except (ConfigError, TlsError) as exc:
            return _fail(args, f"not admitted: {exc}")
        except SessionError as exc:
            return _fail(args, str(exc), status=1)
        decision, started = (both, None) if isinstance(both, Refused) else both
    if isinstance(decision, Refused):
        return _fail(args, f"refused: {decision.message()}", status=1)
    names, admitted = decision.stations, decision.admitted
    print(
        f"mission {decision.mission_id} admitted for drone {args.drone}: a "
        f"{admitted.length_m:.0f} m route"
    )
    ring = " -> ".join(
        f"{names[sid]} (id {sid}, from {admitted.enters_at_m[sid]:.0f} m)" for sid in admitted.ring
    )
    print(f"ring: {ring}")
    first = admitted.first_master
    print(f"first master: {names[first]} (id {first}), the nearest to take-off")
    if started is not None:
        _print_started(started, args.drone_config)
    return 0


def _print_started(started: Started, drone_config: Path | None) -> None:
    """Says where a mission started, and writes the configuration its drone takes its
    ring from (``baton drone --config``) where asked."""
    import json

    mission = started.mission
    ring = ", ".join(
        f"{sid}{' (first master)' if sid == mission.first_master else ''}"
        for sid in mission.live_ring
    )
    print(f"mission {mission.id} of drone {mission.drone} started on stations {ring}")
    if drone_config is not None:
        from baton.lifecycle import write_atomically

        document = started.config.model_dump(mode="json", exclude_unset=True)
        write_atomically(drone_config, json.dumps(document, indent=2) + "\n")
        print(f"the drone's configuration (its ring): {drone_config} (baton drone --config)")


def _missions(args: argparse.Namespace) -> int:
    from baton.config import ConfigError
    from baton.fleet.actions import mission_lines
    from baton.rpc.tls import TlsError

    try:
        network = _network(args) if args.config is not None else None
    except (ConfigError, TlsError) as exc:
        return _fail(args, str(exc))
    lines = mission_lines(args.registry, network)
    if network is None:
        print(f"{'ID':>4}  {'DRONE':<12} {'STATE':<10} {'FIRST':>6}  {'ADMITTED (UTC)':<20} RING")
        for line in lines:
            m = line.mission
            admitted_at = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(m.admitted_at))
            ring = ",".join(map(str, m.live_ring))
            print(
                f"{m.id:>4}  {m.drone:<12} {m.state:<10} {m.first_master:>6}  "
                f"{admitted_at:<20} {ring}"
            )
        return 0
    print(f"{'ID':>4}  {'DRONE':<12} {'STATE':<10} {'MASTER':>6} {'REQNR':>6}  RING")
    silent: set[str] = set()
    for line in lines:
        m, seen = line.mission, line.seen
        if seen is None:
            ring = ",".join(map(str, m.live_ring))
            print(f"{m.id:>4}  {m.drone:<12} {m.state:<10} {'-':>6} {'-':>6}  {ring}")
            continue
        silent.update(seen.silent)
        # A station whose session did not answer is marked with '?'.
        ring = ",".join(f"{sid}{'?' if sid in line.silent_stations else ''}" for sid in m.live_ring)
        master = "?" if seen.master is None else str(seen.master)
        print(f"{m.id:>4}  {m.drone:<12} {seen.state:<10} {master:>6} {seen.reqnr:>6}  {ring}")
    for said in sorted(silent):
        print(f"  {said}")
    return 0


def _status(args: argparse.Namespace) -> int:
    import json

    from google.protobuf.json_format import MessageToDict

    from baton.config import ConfigError
    from baton.fleet.actions import mission_report
    from baton.rpc.tls import TlsError

    if args.config is None:
        return _fail(args, "--config: missing; the network's file with the stations' addresses")
    try:
        network = _network(args)
    except (ConfigError, TlsError) as exc:
        return _fail(args, str(exc))
    report = mission_report(args.registry, args.mission, network)
    mission, drone = report.mission, report.drone
    document = {
        "mission": mission.id,
        "drone": mission.drone,
        "state": mission.state,
        "ring": list(mission.live_ring),
        "departed": list(mission.departed),
        "first_master": mission.first_master,
        "sessions": {
            str(sid): {"error": s} if isinstance(s, str) else MessageToDict(s)
            for sid, s in report.sessions.items()
        },
        "drone_status": {"error": drone} if isinstance(drone, str) else MessageToDict(drone),
    }
    print(json.dumps(document, indent=2))
    return 0


def _drain(args: argparse.Namespace) -> int:
    from baton.config import ConfigError
    from baton.fleet.actions import drain_station
    from baton.rpc.tls import TlsError

    if args.config is None:
        return _fail(args, "--config: missing; the network's file with the stations' addresses")
    try:
        network = _network(args)
    except (ConfigError, TlsError) as exc:
        return _fail(args, str(exc))
    report = drain_station(args.registry, args.station, network)
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


def _start(args: argparse.Namespace) -> int:
    from baton.config import ConfigError
    from baton.fleet.actions import start_mission
    from baton.fleet.sessions import SessionError
    from baton.rpc.tls import TlsError

    if args.config is None:
        return _fail(args, "--config: missing; the network's file with the stations' addresses")
    try:
        started = start_mission(
            args.registry,
            args.mission,
            _network(args),
            args.program,
            args.mission_arg,
            args.drone_address,
        )
    except (ConfigError, TlsError) as exc:
        return _fail(args, str(exc))
    except SessionError as exc:
        return _fail(args, f"mission {args.mission}: {exc}", status=1)
    _print_started(started, args.drone_config)
    return 0


def _cancel(args: argparse.Namespace) -> int:
    from baton.config import ConfigError
    from baton.fleet.actions import cancel_mission
    from baton.fleet.sessions import SessionError
    from baton.rpc.tls import TlsError

    try:
        network = _network(args) if args.config is not None else None
        cancelled = cancel_mission(args.registry, args.mission, network)
    except (ConfigError, TlsError, SessionError) as exc:
        return _fail(args, str(exc))
    mission = cancelled.mission
    if cancelled.stopped_on:
        print(f"mission {mission.id}: sessions stopped on stations {list(cancelled.stopped_on)}")
    print(f"mission {mission.id} of drone {mission.drone} cancelled")
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
    if (problem := _listen_problem(args.listen)) is not None:
        return _fail(args, problem)
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


def _serve(args: argparse.Namespace) -> int:
    from baton import lifecycle
    from baton.config import ConfigError
    from baton.fleet.registry import Registry
    from baton.fleet.service import serve_fleet
    from baton.rpc.tls import OPERATOR, TlsError

    if (problem := _listen_problem(args.listen)) is not None:
        return _fail(args, problem)
    try:
        network = _network(args) if args.config is not None else None
        tls = network.tls if network is not None else tls_from_flags(args, None, OPERATOR)
    except (ConfigError, TlsError) as exc:
        return _fail(args, str(exc))
    Registry(args.registry).close()  # a registry that cannot be used is said now
    try:
        return lifecycle.run(
            serve_fleet(args.registry, network, tls, args.listen, args.address_file)
        )
    except OSError as exc:  # the address cannot be bound: BatonServer says why
        return _fail(args, str(exc))
