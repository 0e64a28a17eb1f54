"""``baton testbed``: the whole system on one machine, with one command."""

from __future__ import annotations

import argparse
import asyncio
import math
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

from baton.controller.cli import add_mission_python, check_mission_python
from baton.sdk.run import add_mission_arg

if TYPE_CHECKING:
    from baton.config import BatonConfig, LinkSpec

DEFAULT_HANDOVER_REQNRS = (90, 180, 270)


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
        "--controllers", type=int, default=3, help="controllers in the ring (default 3)"
    )
    parser.add_argument(
        "--flush-limit",
        default="2MB",
        help="log flush limit with units: 0, 512KB, 2MB (default 2MB)",
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
        "--speedup",
        type=float,
        default=10.0,
        help="simulation speed-up, vehicle and clocks (default 10)",
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
        help="the ArduCopter SITL binary for --vehicle sitl (default: ../shared/sitl/arducopter "
        "beside the checkout)",
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
    parser.add_argument(
        "--grid", type=int, default=5, help="grid size: GRID x GRID waypoints (default 5)"
    )
    parser.add_argument(
        "--length", type=float, default=1500.0, help="corridor length, m (default 1500)"
    )
    parser.add_argument(
        "--spacing", type=float, default=50.0, help="waypoint spacing, m (default 50)"
    )
    parser.add_argument(
        "--altitude", type=float, default=10.0, help="mission altitude, m (default 10)"
    )
    parser.add_argument("--speed", type=float, default=5.0, help="flying speed, m/s (default 5)")
    parser.add_argument(
        "--poll", type=float, default=1.0, help="position poll period, mission s (default 1)"
    )
    parser.add_argument(
        "--link-latency",
        help="controller-to-controller latency (default: the --config file's, else 20ms)",
    )
    parser.add_argument(
        "--link-bandwidth",
        help="controller-to-controller bandwidth (default: the --config file's, else 25Mbit)",
    )
    parser.add_argument(
        "--drone-link-latency",
        help="controller-to-drone latency (default: the --config file's, else 2ms, WiFi-like)",
    )
    parser.add_argument(
        "--drone-link-bandwidth",
        help="controller-to-drone bandwidth (default: the --config file's, else 20Mbit)",
    )
    parser.add_argument("--no-links", action="store_true", help="no link emulation: plain loopback")
    parser.add_argument(
        "--report",
        "--out",
        dest="report",
        default="reports/testbed-report.json",
        help="where to write the JSON report (default reports/testbed-report.json)",
    )
    parser.add_argument(
        "--workdir", help="folder for logs and generated files (default: a new temp folder)"
    )
    parser.add_argument(
        "--timeout", type=float, default=600.0, help="give up after this many seconds (default 600)"
    )
    parser.add_argument(
        "--wait", action="store_true", help="(report) wait for the services to come up and finish"
    )
    parser.set_defaults(run=run)


def _fail(message: str) -> int:
    print(f"baton testbed: {message}", file=sys.stderr)
    return 2


def _link(latency: str | None, bandwidth: str | None, default: LinkSpec) -> LinkSpec:
    """A link from the options, each falling back to ``default``'s value."""
    from baton.config import LinkSpec, parse_duration, parse_rate

    return LinkSpec(
        latency=default.latency if latency is None else parse_duration(latency),
        bandwidth=default.bandwidth if bandwidth is None else parse_rate(bandwidth),
    )


def _vehicle(args: argparse.Namespace, base: BatonConfig | None) -> tuple[str, Path | None]:
    """The planned vehicle ("sim", "sitl" or a URL) and the SITL binary; ValueError says why not."""
    from baton.sitl.launcher import find_binary

    vehicle = args.vehicle
    if vehicle is None:
        named = base is not None and "vehicle_url" in base.drone.model_fields_set
        vehicle = base.drone.vehicle_url if base is not None and named else "sim"
    if vehicle not in ("sim", "sitl") and "://" not in vehicle:
        raise ValueError(
            f"--vehicle {vehicle!r}: expected sim, sitl or a MAVLink URL like "
            "tcpout://127.0.0.1:5760"
        )
    if args.sitl_binary is not None and vehicle != "sitl":
        raise ValueError("--sitl-binary is for --vehicle sitl")
    if vehicle != "sitl":
        return vehicle, None
    binary = Path(args.sitl_binary) if args.sitl_binary else find_binary()
    if binary is None:
        raise ValueError(
            "--vehicle sitl: no SITL binary at ../shared/sitl/arducopter; "
            "pass --sitl-binary PATH (an ArduCopter SITL build)"
        )
    if not binary.is_file():
        raise ValueError(f"--sitl-binary {binary}: no such file")
    if not 0 < args.speedup <= 100:
        raise ValueError(f"--speedup {args.speedup:g}: SITL runs at a speed-up in (0, 100]")
    return vehicle, binary.resolve()


def _mission(mission: str, pairs: list[str]) -> tuple[Path | None, tuple[str, ...], Path | None]:
    """The mission file (None: the survey, grid or corridor), its parameters and the plan
    it flies, from ``--mission``; ValueError says what is wrong (a plan is checked whole
    here, before anything starts)."""
    from baton.missions import plan as plan_mission
    from baton.sdk.run import load_mission, parse_params

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
            plan_mission.load_plan(str(path))
        except plan_mission.PlanError as exc:
            raise ValueError(f"--mission {mission}: {exc}") from None
        flight_plan = path.resolve()
        pairs = [f"plan={flight_plan}", *pairs]
        path = Path(plan_mission.__file__)
    elif path.resolve() == Path(plan_mission.__file__).resolve():
        named = [p.partition("=")[2] for p in pairs if p.startswith("plan=")]
        flight_plan = Path(named[-1]).resolve() if named else None
    try:
        parse_params(load_mission(str(path)), pairs)
    except SystemExit as exc:
        raise ValueError(f"--mission {mission}: {exc}") from None
    return path.resolve(), tuple(pairs), flight_plan


def run(args: argparse.Namespace) -> int:
    """Validates the options, then runs or follows the testbed."""
    from baton.config import MAX_SPEEDUP, ConfigError, load_config, parse_size
    from baton.drone.master import HandoverScriptError, parse_handover_script
    from baton.rpc.tls import INSECURE_WARNING
    from baton.testbed.local import (
        PAPER_CONTROLLER_LINK,
        WIFI_DRONE_LINK,
        MissionPlan,
        TestbedPlan,
    )
    from baton.testbed.run import follow_remote, run_local

    try:
        base = load_config(args.config) if args.config else None
    except ConfigError as exc:
        return _fail(str(exc))
    ids = base.ring_order if base is not None else list(range(args.controllers))
    if base is None and args.controllers < 1:
        return _fail(f"--controllers must be >= 1, got {args.controllers}")
    file_ring = base.controller_link if base is not None and base.controller_link.emulated else None
    file_drone = base.drone_link if base is not None and base.drone_link.emulated else None
    try:
        flush_limit = parse_size(args.flush_limit)
        controller_link = _link(
            args.link_latency, args.link_bandwidth, file_ring or PAPER_CONTROLLER_LINK
        )
        drone_link = _link(
            args.drone_link_latency, args.drone_link_bandwidth, file_drone or WIFI_DRONE_LINK
        )
    except ValueError as exc:
        return _fail(f"bad option value: {exc}")
    if base is not None and args.flush_limit == "2MB":
        flush_limit = base.flush_limit
    handovers: list[tuple[int, int]] = []
    try:
        for text in args.handover:
            reqnr, sep, mid = text.partition(":")
            if not sep or not reqnr.isdigit() or not mid.isdigit():
                raise HandoverScriptError(f"--handover {text!r}: expected REQNR:MID, e.g. 90:1")
            handovers.append((int(reqnr), int(mid)))
        script = "".join(f"{r} {m}\n" for r, m in handovers)
        if args.handover_file:
            script += Path(args.handover_file).read_text()
        scripted = parse_handover_script(script, args.handover_file or "--handover", ids)
    except (HandoverScriptError, OSError) as exc:
        return _fail(str(exc))
    handovers = sorted((reqnr, h.new_master) for reqnr, h in scripted.items())
    ranged = base is not None and base.handover_policy.name != "none"
    if not handovers and not args.no_handovers and not ranged and len(ids) > 1:
        handovers = [
            (reqnr, ids[(k + 1) % len(ids)]) for k, reqnr in enumerate(DEFAULT_HANDOVER_REQNRS)
        ]
    for name in ("speedup", "grid", "length", "spacing", "altitude", "speed", "poll", "timeout"):
        value = getattr(args, name)
        if not 0 < value < math.inf:  # nan too: a --timeout nan never timed out
            return _fail(f"--{name} must be a number > 0 and finite, got {value}")
    if args.speedup > MAX_SPEEDUP:  # checked before anything starts
        return _fail(f"--speedup must be at most {MAX_SPEEDUP:g}, got {args.speedup:g}")
    try:
        vehicle, sitl_binary = _vehicle(args, base)
    except ValueError as exc:
        return _fail(str(exc))
    if args.mission == "corridor" and args.spacing > args.length:
        return _fail(f"--spacing {args.spacing:g} is longer than the corridor (--length)")
    survey = args.mission if args.mission in ("grid", "corridor") else "grid"
    mission = MissionPlan(
        args.grid,
        args.spacing,
        args.altitude,
        args.speed,
        args.poll,
        kind=survey,
        length_m=args.length,
    )
    try:
        mission_file, mission_args, flight_plan = _mission(args.mission, args.mission_arg)
        if args.mission_python is not None:
            check_mission_python(args.mission_python)
    except ValueError as exc:
        return _fail(str(exc))
    report_path = Path(args.report)
    if args.insecure:
        print(f"baton testbed: WARNING: {INSECURE_WARNING}", file=sys.stderr)
    if args.action == "report":
        if base is None:
            return _fail("report needs --config FILE: the testbed to follow")
        if args.insecure:
            tls = base.tls.model_copy(update={"insecure": True})
            base = base.model_copy(update={"tls": tls})
        return asyncio.run(follow_remote(base, args.grid, report_path, args.timeout, handovers))
    plan = TestbedPlan(
        controllers=len(ids),
        flush_limit=flush_limit,
        handovers=tuple(handovers),
        prepared=args.prepared,
        forwarding=args.forwarding,
        speedup=base.speedup if base is not None and args.speedup == 10.0 else args.speedup,
        mission=mission,
        mission_file=mission_file,
        mission_args=mission_args,
        mission_python=None if args.mission_python is None else Path(args.mission_python),
        flight_plan=flight_plan,
        emulate_links=not args.no_links,
        controller_link=controller_link,
        drone_link=drone_link,
        base_config=base,
        vehicle=vehicle,
        sitl_binary=sitl_binary,
        insecure=args.insecure,
    )
    workdir = (
        Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="baton-testbed-"))
    )
    try:
        return asyncio.run(run_local(plan, workdir, report_path, args.timeout))
    except KeyboardInterrupt:
        print("baton testbed: interrupted; every process stopped", file=sys.stderr)
        return 130
