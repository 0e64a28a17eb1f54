"""``baton testbed``: the whole system on one machine, with one command."""

from __future__ import annotations

import argparse
import asyncio
import math
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

from baton.config import BatonConfig
from baton.controller.cli import add_mission_python, check_mission_python
from baton.sdk.run import add_mission_arg
from baton.testbed.local import (
    DEFAULT_CONTROLLERS,
    DEFAULT_SPEEDUP,
    PAPER_CONTROLLER_LINK,
    WIFI_DRONE_LINK,
    MissionPlan,
)

if TYPE_CHECKING:
    from baton.testbed.local import TestbedPlan

# Where the run writes its report (and the map and page beside it), by default.
DEFAULT_REPORT, DEFAULT_FLEET_REPORT = "reports/testbed-report.json", "reports/fleet-report.json"
DEFAULT_HANDOVER_REQNRS = (90, 180, 270)
# For --help: BatonConfig's flush limit default (in MiB, as 2MB parses), the testbed's too.
DEFAULT_FLUSH_LIMIT = f"{BatonConfig.model_fields['flush_limit'].default / 2**20:g}MB"
# The survey flags and the MissionPlan fields they set (its defaults are the flags').
MISSION_FIELDS = {
    "grid": "grid",
    "length": "length_m",
    "spacing": "spacing_m",
    "altitude": "altitude_m",
    "speed": "speed_m_s",
    "poll": "poll_s",
}


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Adds ``baton testbed``."""
    parser = subparsers.add_parser(
        "testbed",
        help="run the paper's grid mission on a local testbed and report",
        description=(
            "Starts the sim vehicle, the drone service, N controllers each running the paper's "
            "grid mission, and a link emulator on every link, as processes on loopback; runs the "
            "mission with the given handovers; prints a summary and writes a JSON report. "
            "'baton testbed report --config FILE' instead follows a testbed running elsewhere "
            "(the compose testbed) and writes the same report."
        ),
    )
    parser.add_argument(
        "action",
        nargs="?",
        choices=["run", "report"],
        default="run",
        help="run (default): start and run a local testbed; report: follow one started elsewhere",
    )
    parser.add_argument(
        "--controllers",
        type=int,
        help=f"controllers in the ring (default: the --config file's, else {DEFAULT_CONTROLLERS})",
    )
    parser.add_argument(
        "--flush-limit",
        help="log flush limit with units: 0, 512KB, 2MB (default: the --config file's, else "
        f"{DEFAULT_FLUSH_LIMIT})",
    )
    parser.add_argument(
        "--handover",
        action="append",
        default=[],
        metavar="REQNR:MID",
        help="hand over to controller MID right after request REQNR; repeatable "
        f"(default: after requests {', '.join(map(str, DEFAULT_HANDOVER_REQNRS))} to the next "
        "controller each time)",
    )
    parser.add_argument(
        "--handover-file", help="handovers as 'REQNR MID' lines (the drone's format)"
    )
    parser.add_argument(
        "--no-handovers",
        action="store_true",
        help="run without any scripted handover (the default when the --config file names a "
        "handover_policy: the drone then picks its masters)",
    )
    parser.add_argument(
        "--prepared",
        action="store_true",
        help="prepare the scripted handovers: the new master is caught up while the mission "
        "goes on, and the drone moves the master once it has (docs/design.md)",
    )
    parser.add_argument(
        "--forwarding",
        choices=("cut-through", "store-and-forward"),
        default=None,
        help="the ring's forwarding (default: the testbed file's, else cut-through; "
        "store-and-forward is the paper's)",
    )
    parser.add_argument(
        "--insecure",
        action="store_true",
        help="every part plain, no certificates (debugging only: anyone on the network may "
        "then command the drone); by default every part gets a certificate, from the "
        "--config file's tls.certs folder or made in the workdir",
    )
    parser.add_argument(
        "--config", help="a full testbed YAML (endpoints, ring, initial master, locations, links)"
    )
    parser.add_argument(
        "--fleet",
        type=Path,
        metavar="FILE",
        help="fly a fleet instead: the file's stations (baton station) and drones, each with "
        "its sim vehicle, drone service and survey, every mission admitted over the stations "
        "first (examples/fleet.yaml); per-mission results and a fleet summary; the other "
        "mission options do not apply",
    )
    parser.add_argument(
        "--external",
        type=Path,
        metavar="FILE",
        help="with --fleet: fly it on stations and drone services that run already (the "
        "compose fleet, deploy/compose.ci.fleet.yml) at the addresses FILE gives (certs: the "
        "folder, stations: id -> HOST:PORT, drones: name -> HOST:PORT); the workdir, shared "
        "with the drones and their vehicles, gets each drone's configuration (NAME/drone.json) "
        "and then network.yaml, and is where they count their effects",
    )
    parser.add_argument(
        "--admit",
        action="store_true",
        help="take the ring and the initial master from mission admission: the --config "
        "file's controllers are the stations (location, range_m), the route is the mission's "
        "(grid, corridor or a plan) from drone.home; the ring is the controllers covering it "
        "in route order, the first master the nearest to take-off, the others are not "
        "started; a route with a stretch no controller covers is refused, naming it, before "
        "anything starts",
    )
    parser.add_argument(
        "--speedup",
        type=float,
        help="simulation speed-up, vehicle and clocks (default: the --config file's, else "
        f"{DEFAULT_SPEEDUP:g})",
    )
    parser.add_argument(
        "--vehicle",
        metavar="sim|sitl|URL",
        help="the autopilot: 'sim' starts the embedded sim vehicle, 'sitl' starts ArduPilot "
        "Copter SITL at the same speed-up, a MAVLink URL (tcpout://HOST:5760, udpin://...) "
        "flies one that runs already (default: the --config file's drone.vehicle_url if it "
        "names one, else sim)",
    )
    parser.add_argument(
        "--sitl-binary",
        metavar="PATH",
        help="the ArduCopter SITL binary for --vehicle sitl (default: $BATON_SITL_BINARY, "
        "else arducopter on PATH)",
    )
    parser.add_argument(
        "--mission",
        metavar="grid|corridor|FILE",
        default="grid",
        help="what the controllers fly: the paper's grid survey (default, --grid ...), a "
        "corridor survey (a line of --length metres east of the take-off point; "
        "examples/corridor.yaml places stations along it), a mission file (defines "
        "mission(drone, **params)), or a QGroundControl plan (.plan, or a 'QGC WPL 110' "
        "waypoint file) flown by baton/missions/plan.py",
    )
    add_mission_arg(parser)
    add_mission_python(parser)
    survey = MissionPlan()
    for flag, kind, what in (
        ("grid", int, "grid size: GRID x GRID waypoints"),
        ("length", float, "corridor length, m"),
        ("spacing", float, "waypoint spacing, m"),
        ("altitude", float, "mission altitude, m"),
        ("speed", float, "flying speed, m/s"),
        ("poll", float, "position poll period, mission s"),
    ):
        default = getattr(survey, MISSION_FIELDS[flag])
        parser.add_argument(f"--{flag}", type=kind, help=f"{what} (default {default:g})")
    parser.add_argument(
        "--link-latency",
        help="controller-to-controller latency (default: the --config file's, else "
        f"{PAPER_CONTROLLER_LINK.latency * 1e3:g}ms)",
    )
    parser.add_argument(
        "--link-bandwidth",
        help="controller-to-controller bandwidth (default: the --config file's, else "
        f"{(PAPER_CONTROLLER_LINK.bandwidth or 0) / 1e6:g}Mbit)",
    )
    parser.add_argument(
        "--drone-link-latency",
        help="controller-to-drone latency (default: the --config file's, else "
        f"{WIFI_DRONE_LINK.latency * 1e3:g}ms, WiFi-like)",
    )
    parser.add_argument(
        "--drone-link-bandwidth",
        help="controller-to-drone bandwidth (default: the --config file's, else "
        f"{(WIFI_DRONE_LINK.bandwidth or 0) / 1e6:g}Mbit)",
    )
    parser.add_argument("--no-links", action="store_true", help="no link emulation: plain loopback")
    parser.add_argument(
        "--report",
        "--out",
        dest="report",
        default=None,
        help=f"where to write the JSON report, the map (.geojson, .png) and the HTML page "
        f"beside it (default {DEFAULT_REPORT}; with --fleet, {DEFAULT_FLEET_REPORT})",
    )
    parser.add_argument(
        "--workdir", help="folder for logs and generated files (default: a new temp folder)"
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=600.0,
        help="give up after this many seconds (default 600)",
    )
    parser.add_argument(
        "--wait", action="store_true", help="(report) wait for the services to come up and finish"
    )
    parser.add_argument(
        "--fault",
        action="append",
        default=[],
        metavar="KIND:PART@WHEN[,for=DURATION][,to=PERCENT]",
        help="inject a fault, repeatable: kill (kill -9), stop (SIGSTOP, then SIGCONT after "
        "for=), cut (a link emulator: link-ring-N, link-drone-N) or full (controller-N's disk "
        "fills: its log file can grow no more) of a part (controller-N, "
        "drone, sim-vehicle, a link), or the operator's pause (resumed after for=), abort or "
        "land-now to the drone, or battery (the sim vehicle's battery reads to=PERCENT from "
        "then on: the drone's battery failsafe acts below safety.battery_reserve), after the "
        "drone served request N (@reqnr=N) or at a "
        "time after the mission started (@t=30s); for=DURATION ends it (a killed part is "
        "restarted); e.g. kill:controller-1@reqnr=130, stop:controller-0@reqnr=60,for=20s, "
        "cut:link-ring-1@reqnr=90,for=10s, full:controller-1@reqnr=40, "
        "battery:sim-vehicle@reqnr=20,to=15%%. Each is in the report with the mission's verdict",
    )
    parser.add_argument(
        "--gcs",
        action="append",
        metavar="udp:HOST:PORT",
        help="a ground station watching live: the drone forwards the autopilot's MAVLink there "
        "(QGroundControl: udp:127.0.0.1:14550), repeatable; its commands are refused unless "
        "--gcs-override (default: the --config file's drone.gcs, else none)",
    )
    parser.add_argument(
        "--gcs-override",
        action="store_true",
        help="a ground station's command is an operator override that pauses the mission",
    )
    parser.add_argument(
        "--autopilot-gcs-timeout",
        metavar="DURATION",
        help="the autopilot's own GCS failsafe (it returns the vehicle when the drone service "
        "is silent this long, in mission time; never under a restart of the drone service): "
        "e.g. 30s, 10min; 0 leaves the autopilot's own setting (default: the --config file's "
        "safety.autopilot_gcs_timeout, else 10s)",
    )
    parser.add_argument(
        "--restart-parts",
        action="store_true",
        help="start a part that dies (killed from outside or by --fault kill) again with its "
        "command line, as a supervisor would (a controller keeps its log file, the drone its "
        "state); without it a dead part is reported and the run goes on while the mission can",
    )
    parser.set_defaults(run=run)


def _fail(message: str) -> int:
    print(f"baton testbed: {message}", file=sys.stderr)
    return 2


def _vehicle(args: argparse.Namespace, config: BatonConfig) -> tuple[str, Path | None]:
    """The planned vehicle ("sim", "sitl" or a URL) and the SITL binary; ValueError says why not."""
    from baton.sitl.launcher import SitlBinaryNotFound, find_binary

    vehicle = args.vehicle
    if vehicle is None:
        named = "vehicle_url" in config.drone.model_fields_set
        vehicle = config.drone.vehicle_url if named else "sim"
    if vehicle not in ("sim", "sitl") and "://" not in vehicle:
        raise ValueError(
            f"--vehicle {vehicle!r}: expected sim, sitl or a MAVLink URL like "
            "tcpout://127.0.0.1:5760"
        )
    if args.sitl_binary is not None and vehicle != "sitl":
        raise ValueError("--sitl-binary is for --vehicle sitl")
    if vehicle != "sitl":
        return vehicle, None
    try:
        binary = find_binary(args.sitl_binary, os.environ)
    except SitlBinaryNotFound as exc:
        raise ValueError(f"--vehicle sitl: {exc}") from None
    if not 0 < config.speedup <= 100:
        raise ValueError(f"--speedup {config.speedup:g}: SITL runs at a speed-up in (0, 100]")
    return vehicle, binary


def _mission(mission: str, pairs: list[str]) -> tuple[Path | None, tuple[str, ...], Path | None]:
    """The mission file (None: the survey, grid or corridor), its parameters and the plan
    it flies, from ``--mission``; ValueError says what is wrong (a plan is checked whole
    here, before anything starts)."""
    from baton.missions import plan as plan_mission
    from baton.sdk.run import MissionLoadError, load_mission, parse_params

    if mission in ("grid", "corridor"):
        if pairs:
            raise ValueError("--mission-arg is for a --mission FILE")
        return None, (), None
    path = Path(mission)
    if not path.is_file():
        raise ValueError(f"--mission {mission}: no such file")
    flight_plan = None
    if path.suffix != ".py":  # a QGroundControl plan, flown by the plan mission
        try:
            ends = [p.partition("=")[2] for p in pairs if p.startswith("end=")]
            plan_mission.load_plan(str(path), ends[-1] if ends else "")
        except plan_mission.PlanError as exc:
            raise ValueError(f"--mission {mission}: {exc}") from None
        flight_plan = path.resolve()
        pairs = [f"plan={flight_plan}", *pairs]
        path = Path(plan_mission.__file__)
    elif path.resolve() == Path(plan_mission.__file__).resolve():
        named = [p.partition("=")[2] for p in pairs if p.startswith("plan=")]
        flight_plan = Path(named[-1]).resolve() if named else None
    try:
        loaded = load_mission(str(path))
    except MissionLoadError as exc:  # names the file, the line and the cause
        raise ValueError(f"--mission: {exc}") from None
    try:
        parse_params(loaded, pairs)
    except SystemExit as exc:
        raise ValueError(f"--mission {mission}: {exc}") from None
    return path.resolve(), tuple(pairs), flight_plan


def testbed_config(args: argparse.Namespace) -> tuple[BatonConfig, bool]:
    """The one model the testbed runs with: the --config file (else ``--controllers``
    controllers), the testbed's own defaults where the file says nothing (its links, and
    its speed-up when there is no file), then every flag that was given; and whether a
    file was given. ConfigError names the file or the flag and the fix."""
    from baton.config import ConfigError, controllers_only, load_config, merge
    from baton.testbed.local import with_testbed_defaults

    if args.config:
        config = load_config(args.config)
        if args.controllers is not None and args.controllers != len(config.controllers):
            raise ConfigError(
                f"--controllers {args.controllers}: {args.config} lists "
                f"{len(config.controllers)} controllers; drop --controllers or edit the file"
            )
    else:
        count = DEFAULT_CONTROLLERS if args.controllers is None else args.controllers
        if count < 1:
            raise ConfigError(f"--controllers must be >= 1, got {count}")
        config = controllers_only(range(count))
    config = with_testbed_defaults(config, from_file=bool(args.config))
    flags = [
        ("--flush-limit", "flush_limit", args.flush_limit),
        ("--speedup", "speedup", args.speedup),
        ("--forwarding", "ring.forwarding", args.forwarding),
        ("--link-latency", "controller_link.latency", args.link_latency),
        ("--link-bandwidth", "controller_link.bandwidth", args.link_bandwidth),
        ("--drone-link-latency", "drone_link.latency", args.drone_link_latency),
        ("--drone-link-bandwidth", "drone_link.bandwidth", args.drone_link_bandwidth),
        ("--insecure", "tls.insecure", True if args.insecure else None),
        ("--gcs", "drone.gcs", args.gcs),
        ("--gcs-override", "drone.gcs_override", True if args.gcs_override else None),
        ("--autopilot-gcs-timeout", "safety.autopilot_gcs_timeout", args.autopilot_gcs_timeout),
    ]
    return merge(config, flags, args.config or ""), bool(args.config)


def _admitted(args: argparse.Namespace, config: BatonConfig) -> BatonConfig:
    """``config`` with the ring and the initial master of mission admission over its
    controllers (``--admit``), said on stdout; ValueError or ConfigError say why not."""
    from baton.config import ConfigError
    from baton.fleet.routes import plan_route, survey_route
    from baton.missions.plan import load_plan
    from baton.sdk.types import Position
    from baton.testbed import admission

    if not args.config:
        raise ConfigError("--admit needs --config FILE: its controllers' locations and ranges")
    home = Position(config.drone.home.latitude_deg, config.drone.home.longitude_deg)
    if args.mission in ("grid", "corridor"):
        route = survey_route(home, _survey(args).targets())
    else:
        _, _, flight_plan = _mission(args.mission, args.mission_arg)
        if flight_plan is None:
            raise ValueError(
                "--admit needs the mission's route before it flies: --mission grid, corridor "
                "or a QGroundControl plan; a mission program's route is known only as it flies"
            )
        route = plan_route(load_plan(str(flight_plan)), home)
    admitted, decision = admission.admitted_config(config, route, args.config)
    print(f"baton testbed: {admission.describe(admitted, config, decision)}")
    return admitted


def _survey(args: argparse.Namespace) -> MissionPlan:
    """The survey flown (grid or corridor) with the flags' parameters."""
    survey = {MISSION_FIELDS[f]: v for f in MISSION_FIELDS if (v := getattr(args, f)) is not None}
    return MissionPlan(
        **survey, kind=args.mission if args.mission in ("grid", "corridor") else "grid"
    )


def _check_numbers(args: argparse.Namespace) -> None:
    """The numeric flags, before anything starts; ValueError says which and why."""
    from baton.config import MAX_SPEEDUP

    for name in ("speedup", *MISSION_FIELDS, "timeout"):
        value = getattr(args, name)
        if value is not None and not 0 < value < math.inf:  # nan too: a --timeout nan never ended
            raise ValueError(f"--{name} must be a number > 0 and finite, got {value}")
    if args.speedup is not None and args.speedup > MAX_SPEEDUP:
        raise ValueError(f"--speedup must be at most {MAX_SPEEDUP:g}, got {args.speedup:g}")


def _handovers(args: argparse.Namespace, config: BatonConfig) -> list[tuple[int, int]]:
    """The scripted handovers (after reqnr, new master): the flags' and the file's, else
    the default round trip unless a policy or --no-handovers says none.
    HandoverScriptError or OSError say what is wrong."""
    from baton.drone.master import HandoverScriptError, parse_handover_script

    ids = config.ring_order
    handovers: list[tuple[int, int]] = []
    for text in args.handover:
        reqnr, sep, mid = text.partition(":")
        if not sep or not reqnr.isdigit() or not mid.isdigit():
            raise HandoverScriptError(f"--handover {text!r}: expected REQNR:MID, e.g. 90:1")
        handovers.append((int(reqnr), int(mid)))
    script = "".join(f"{r} {m}\n" for r, m in handovers)
    if args.handover_file:
        script += Path(args.handover_file).read_text()
    scripted = parse_handover_script(script, args.handover_file or "--handover", ids)
    handovers = sorted((reqnr, h.new_master) for reqnr, h in scripted.items())
    ranged = config.handover_policy.name != "none"
    if not handovers and not args.no_handovers and not ranged and len(ids) > 1:
        handovers = [
            (reqnr, ids[(k + 1) % len(ids)]) for k, reqnr in enumerate(DEFAULT_HANDOVER_REQNRS)
        ]
    return handovers


def _plan(
    args: argparse.Namespace, config: BatonConfig, from_file: bool, handovers: list[tuple[int, int]]
) -> TestbedPlan:
    """What the local testbed runs; ValueError says which option is wrong."""
    from baton.testbed.faults import parse_fault
    from baton.testbed.local import TestbedPlan

    vehicle, sitl_binary = _vehicle(args, config)
    mission = _survey(args)
    if args.mission == "corridor" and mission.spacing_m > mission.length_m:
        raise ValueError(f"--spacing {mission.spacing_m:g} is longer than the corridor (--length)")
    mission_file, mission_args, flight_plan = _mission(args.mission, args.mission_arg)
    if args.mission_python is not None:
        check_mission_python(args.mission_python)
    return TestbedPlan(
        config=config,
        from_file=from_file,
        handovers=tuple(handovers),
        prepared=args.prepared,
        mission=mission,
        mission_file=mission_file,
        mission_args=mission_args,
        mission_python=None if args.mission_python is None else Path(args.mission_python),
        flight_plan=flight_plan,
        emulate_links=not args.no_links,
        vehicle=vehicle,
        sitl_binary=sitl_binary,
        keep_going=True,
        restart_parts=args.restart_parts,
        faults=tuple(parse_fault(text) for text in args.fault),
    )


def run(args: argparse.Namespace) -> int:
    """Validates the options, then runs or follows the testbed."""
    from baton.config import ConfigError
    from baton.drone.master import HandoverScriptError
    from baton.rpc.tls import INSECURE_WARNING
    from baton.testbed import run as running
    from baton.testbed.faults import check_parts

    if args.action == "report" and args.admit:
        return _fail("--admit is for a local run: 'report' follows the ring the file started")
    if args.external is not None and args.fleet is None:
        return _fail("--external FILE names where a fleet's parts run: give --fleet FILE too")
    if args.fleet is not None:
        return _run_fleet(args)
    try:
        _check_numbers(args)
        config, from_file = testbed_config(args)
        if args.admit:
            config = _admitted(args, config)
        handovers = _handovers(args, config)
        plan = _plan(args, config, from_file, handovers)
        check_parts(plan.faults, plan.part_names())
    except (ConfigError, HandoverScriptError, OSError, ValueError) as exc:
        return _fail(str(exc))
    if args.action == "report" and (plan.faults or args.restart_parts):
        return _fail("--fault and --restart-parts are for a local run, not 'report'")
    report_path = Path(args.report or DEFAULT_REPORT)
    if args.insecure:
        print(f"baton testbed: WARNING: {INSECURE_WARNING}", file=sys.stderr)
    if args.action == "report":
        if not from_file:
            return _fail("report needs --config FILE: the testbed to follow")
        return asyncio.run(
            running.follow_remote(config, plan.mission, report_path, args.timeout, handovers)
        )
    workdir = (
        Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="baton-testbed-"))
    )
    try:
        return asyncio.run(running.run_local(plan, workdir, report_path, args.timeout))
    except KeyboardInterrupt:
        print("baton testbed: interrupted; every process stopped", file=sys.stderr)
        return 130


def _run_fleet(args: argparse.Namespace) -> int:
    """``--fleet FILE``: the fleet testbed (testbed/fleet.py) to its end."""
    from baton.config import ConfigError
    from baton.fleet.sessions import SessionError
    from baton.testbed.fleet import (
        NETWORK_FILE,
        REGISTRY_FILE,
        describe,
        fleet_report,
        load_fleet,
        run_fleet,
    )
    from baton.testbed.fleet_external import load_external, run_external_fleet
    from baton.testbed.fleet_report import write_fleet_report

    if args.action == "report":
        return _fail("--fleet is for a local run")
    try:
        fleet = load_fleet(args.fleet)
        parts = load_external(args.external, fleet) if args.external is not None else None
    except ConfigError as exc:
        return _fail(str(exc))
    workdir = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="baton-fleet-"))
    print(
        f"baton testbed: fleet of {len(fleet.drones)} drones over {len(fleet.stations)} "
        f"stations, speed-up {fleet.speedup:g}x; "
        + (f"logs in {workdir / 'parts'}\n" if parts is None else f"parts at {args.external}\n")
        + f"baton testbed: watch it live: baton fleet view --registry {workdir / REGISTRY_FILE} "
        f"--config {workdir / NETWORK_FILE}",
        flush=True,
    )
    started = time.monotonic()
    try:
        if parts is None:
            run = asyncio.run(run_fleet(fleet, workdir, args.timeout))
        else:
            run = asyncio.run(run_external_fleet(fleet, parts, workdir, args.timeout))
    except ValueError as exc:
        return _fail(str(exc))
    except (TimeoutError, SessionError) as exc:
        print(f"baton testbed: the fleet did not fly: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("baton testbed: interrupted; every process stopped", file=sys.stderr)
        return 130
    elapsed = time.monotonic() - started
    print(describe(run.results, elapsed), flush=True)
    report_path = Path(args.report or DEFAULT_FLEET_REPORT)
    map_path, png_path, page = write_fleet_report(
        report_path, fleet_report(fleet, run, elapsed), run.network, run.flights
    )
    print(f"report: {report_path}\nmap: {map_path} (GeoJSON), {png_path}\nHTML report: {page}")
    return 0 if all(r.ok for r in run.results) else 1
