"""``baton drone``: the drone service on the drone's companion computer."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from baton.certs.cli import add_tls_flags, tls_from_flags
from baton.drone.camera import DEFAULT_RESOLUTION

if TYPE_CHECKING:
    from baton.config import BatonConfig
    from baton.drone.gcs import GcsLink
    from baton.drone.policy import PolicyParams, Station
    from baton.drone.settings import DroneSettings


def _controller_ids(text: str) -> tuple[int, ...]:
    try:
        ids = tuple(int(part) for part in text.split(",") if part.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated controller ids like '0,1,2', got {text!r}"
        ) from None
    if not ids or len(set(ids)) != len(ids) or min(ids) < 0:
        raise argparse.ArgumentTypeError(
            f"expected distinct non-negative controller ids like '0,1,2', got {text!r}"
        )
    return ids


def _resolution(text: str) -> tuple[int, int]:
    from baton.drone.camera import parse_resolution

    try:
        return parse_resolution(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _address(text: str) -> str:
    from baton.config import parse_address

    try:
        return parse_address(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


# The connection URLs MAVSDK takes (MAVSDK's CliArg).
VEHICLE_SCHEMES = ("udp", "udpin", "udpout", "tcp", "tcpin", "tcpout", "serial")


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Adds ``baton drone`` and its options."""
    width, height = DEFAULT_RESOLUTION
    parser = subparsers.add_parser(
        "drone",
        help="the drone service: executes the master controller's drone-API calls",
        description="Serves baton.v1.Drone (Invoke, Connect, Handover, GetStatus) in front of "
        "a MAVLink vehicle (MAVSDK) and a local camera image source. Flags override the "
        "values of --config.",
    )
    parser.add_argument(
        "--config",
        metavar="FILE",
        help="testbed YAML (baton.config): drone address, vehicle URL, controllers, "
        "initial master, speed-up",
    )
    parser.add_argument(
        "--address",
        type=_address,
        help="HOST:PORT to serve on; port 0 picks a free port (default: config, else "
        "127.0.0.1:50051)",
    )
    parser.add_argument(
        "--address-file",
        metavar="PATH",
        help="write the bound HOST:PORT to this file once serving (useful with port 0)",
    )
    parser.add_argument(
        "--vehicle-url",
        metavar="URL",
        help="MAVSDK connection URL of the autopilot, e.g. udpout://127.0.0.1:14550 "
        "(default: config, else udpin://127.0.0.1:14540)",
    )
    parser.add_argument(
        "--mavlink-key",
        metavar="FILE",
        help="sign MAVLink to the autopilot and accept only signed MAVLink from it, with "
        "this key (baton certs mavlink-key FILE; default: the config's drone.mavlink_key, "
        "else unsigned). The autopilot must hold the same key",
    )
    parser.add_argument(
        "--tlog-dir",
        metavar="DIR",
        help="record the MAVLink traffic with the autopilot as a telemetry log (.tlog, as "
        "QGroundControl and pymavlink's mavlogdump.py read it), one file per run in DIR "
        "(default: none recorded)",
    )
    parser.add_argument(
        "--gcs",
        action="append",
        metavar="udp:HOST:PORT",
        help="forward the autopilot's MAVLink to a ground station listening there (QGroundControl, "
        "MAVProxy: udp:127.0.0.1:14550), repeatable; its commands are refused (watch only) "
        "unless --gcs-override (default: the config's drone.gcs, else none)",
    )
    parser.add_argument(
        "--gcs-override",
        action="store_true",
        help="a ground station's command is an operator override: passed to the autopilot, and "
        "the mission paused (the master's next call refused FAILED_PRECONDITION) (default: the "
        "config's drone.gcs_override, else watch only)",
    )
    parser.add_argument(
        "--controllers",
        type=_controller_ids,
        metavar="IDS",
        help="comma-separated controller ids that may become master, e.g. 0,1,2 "
        "(default: the config's controllers, else 0)",
    )
    parser.add_argument(
        "--initial-master",
        type=int,
        metavar="ID",
        help="the first master (default: config's initial_master, else the first controller)",
    )
    parser.add_argument(
        "--handover-file",
        metavar="FILE",
        help="handover script: lines 'REQNR ID' = hand over to controller ID right after "
        "serving request REQNR ('#' comments and blank lines allowed)",
    )
    parser.add_argument(
        "--image",
        metavar="FILE",
        help="serve this image file for every picture instead of a generated PPM",
    )
    parser.add_argument(
        "--resolution",
        type=_resolution,
        default=DEFAULT_RESOLUTION,
        metavar="WxH",
        help=f"initial resolution of generated pictures, 16..8192 per side "
        f"(default: {width}x{height}, about 1 MB)",
    )
    parser.add_argument(
        "--camera-effects-file",
        metavar="PATH",
        help="append one JSON line per picture the camera produced (seq, time, resolution, "
        "bytes), flushed at once, for an exactly-once check independent of the drone's audit; "
        "a restarted drone continues the file (default: none written)",
    )
    parser.add_argument(
        "--thumbnails-dir",
        metavar="DIR",
        help="keep a thumbnail of each picture in DIR (JPEG, 96 pixels a side, about 3 KB, "
        "the first 500 of a run; picture-SEQ.jpg by the camera effects file's seq), for the "
        "testbed's HTML report (default: none kept; the pictures themselves never are)",
    )
    parser.add_argument(
        "--speedup",
        type=float,
        metavar="X",
        help="simulation speed-up of the vehicle, for the logs and status "
        "(default: config, else 1)",
    )
    parser.add_argument(
        "--force-race",
        choices=["notice-first", "reply-first"],
        help="fault injection for tests: at every scripted handover, hold back the reply "
        "(notice-first) or the handover notice (reply-first) for --race-delay seconds, so "
        "the race of footnote 2 goes the chosen way (default: no hold-back)",
    )
    parser.add_argument(
        "--race-delay",
        type=float,
        default=0.2,
        help="seconds the other message is held back under --force-race (default 0.2)",
    )
    parser.add_argument(
        "--cache-window",
        type=int,
        default=None,
        metavar="K",
        help="replies kept for duplicate requests (default: 16; see baton/drone/dedupe.py)",
    )
    parser.add_argument(
        "--takeover-after",
        metavar="DURATION",
        help="take the master over when the drone has not seen it (no stream, no request) "
        "for this long, in mission seconds, e.g. 3s; 0 never (default: config, else 3s)",
    )
    parser.add_argument(
        "--handover-policy",
        choices=["none", "nearest", "predictive"],
        help="who the drone makes master as it flies, from its own position and every "
        "controller's location and range (the --config file's): 'nearest' with hysteresis, "
        "'predictive' from the velocity; 'none' leaves it to --handover-file and the Handover "
        "RPC, which override a policy too (default: the config's handover_policy, else none)",
    )
    add_tls_flags(parser)
    parser.add_argument(
        "--state",
        metavar="FILE",
        help="keep the drone's state (master, last request number, reply cache, audit, "
        "handover-script position, the request being executed) in this SQLite file and "
        "resume from it at start, so a restart or a kill -9 loses none of it; without it "
        "the state lives in memory only (see baton/drone/store.py)",
    )
    parser.set_defaults(run=run)


def settings_from_args(args: argparse.Namespace) -> DroneSettings:
    """DroneSettings from the flags merged over the optional configuration file
    (``baton.config.merge``); ConfigError or ValueError names the flag and the fix."""
    from baton.config import controllers_only, load_config, merge
    from baton.drone.dedupe import DEFAULT_WINDOW
    from baton.drone.master import load_handover_script
    from baton.drone.mavlink_relay import VehicleEndpoint
    from baton.drone.settings import DroneSettings, Race
    from baton.signing import read_key

    if args.config:
        config = load_config(args.config)
    else:
        if args.handover_policy not in (None, "none"):
            raise ValueError(
                f"--handover-policy {args.handover_policy} needs --config: the testbed file "
                "with every controller's location and range_m"
            )
        config = controllers_only(args.controllers or (0,))
    # Without a file the ids made the model; with one they are its ring order.
    order = list(args.controllers) if args.config and args.controllers else None
    flags = [
        ("--address", "drone.address", args.address),
        ("--vehicle-url", "drone.vehicle_url", args.vehicle_url),
        ("--mavlink-key", "drone.mavlink_key", args.mavlink_key),
        ("--gcs", "drone.gcs", args.gcs),
        ("--gcs-override", "drone.gcs_override", True if args.gcs_override else None),
        ("--controllers", "ring.order", order),
        ("--initial-master", "initial_master", args.initial_master),
        ("--speedup", "speedup", args.speedup),
        ("--takeover-after", "takeover_after", args.takeover_after),
        ("--handover-policy", "handover_policy.name", args.handover_policy),
    ]
    config = merge(config, flags, args.config or "")
    if not 0 <= args.race_delay <= 60:
        raise ValueError(f"--race-delay must be in 0..60 seconds, got {args.race_delay}")
    if args.cache_window is not None and args.cache_window < 1:
        raise ValueError(f"--cache-window must be >= 1, got {args.cache_window}")
    controllers = tuple(config.ring_order)
    script = load_handover_script(args.handover_file, controllers) if args.handover_file else {}
    policy, stations = handover_policy(config)
    if args.image is not None:
        try:
            with open(args.image, "rb"):
                pass
        except OSError as exc:
            raise ValueError(
                f"--image {args.image}: cannot read it ({exc.strerror}); give an image file, "
                "or leave --image out for generated pictures"
            ) from None
    vehicle = config.drone.vehicle_url
    if vehicle.split("://", 1)[0] not in VEHICLE_SCHEMES or "://" not in vehicle:
        raise ValueError(
            f"--vehicle-url {vehicle}: not a MAVLink URL; use one of "
            f"{', '.join(s + '://' for s in VEHICLE_SCHEMES)}, e.g. udpin://0.0.0.0:14540"
        )
    mavlink_key = None
    if config.drone.mavlink_key is not None:
        mavlink_key = read_key(config.drone.mavlink_key)
        VehicleEndpoint.parse(vehicle)  # the relay can hold it, or a message saying why
    if args.tlog_dir is not None or config.drone.gcs:
        VehicleEndpoint.parse(vehicle, tlog=True)  # the relay holds it, or a message why
    return DroneSettings(
        config=config,
        handover_script=script,
        image_file=args.image,
        resolution=args.resolution,
        cache_window=args.cache_window or DEFAULT_WINDOW,
        address_file=args.address_file,
        race=Race(args.force_race, args.race_delay) if args.force_race else None,
        state_file=args.state,
        camera_effects_file=args.camera_effects_file,
        thumbnails_dir=args.thumbnails_dir,
        tls=tls_from_flags(args, config, config.drone_identity),
        mavlink_key=mavlink_key,
        policy=policy,
        stations=stations,
    )


def handover_policy(config: BatonConfig) -> tuple[PolicyParams | None, dict[int, Station]]:
    """The policy the drone runs (the model's, flag merged in) and every controller's
    station (the model has checked that each has a location and a range)."""
    from baton.drone.policy import PolicyParams, Station
    from baton.drone.settings import link_bounds
    from baton.sdk import Position

    chosen = config.handover_policy
    if chosen.name == "none":
        return None, {}
    stations = {}
    for c in config.controllers:
        assert c.location is not None and c.range_m is not None
        where = Position(c.location.latitude_deg, c.location.longitude_deg)
        stations[c.id] = Station(c.id, where, c.range_m)
    params = PolicyParams(
        chosen.name,
        margin_m=chosen.margin_m,
        dwell_s=chosen.dwell,
        lead_s=chosen.lead,
        link_up_s=chosen.link_up,
        # A master's link down while in range is lost after the takeover time, as
        # the takeover watch counts it.
        link_lost_after_s=config.takeover_after,
        link_bounds=link_bounds(config),
    )
    return params, stations


def ground_stations(settings: DroneSettings) -> GcsLink | None:
    """The ground stations the configuration names (drone.gcs, --gcs), signed with the
    mission's key when signing is on; None without any."""
    from baton.drone.gcs import GcsEndpoint, GcsLink
    from baton.signing import Signer

    drone = settings.config.drone
    if not drone.gcs:
        return None
    key = settings.mavlink_key
    return GcsLink(
        [GcsEndpoint.parse(text) for text in drone.gcs],
        override=drone.gcs_override,
        signer=Signer(key, link_id=2) if key is not None else None,
    )


def run(args: argparse.Namespace) -> int:
    """Runs the drone service until SIGINT/SIGTERM."""

    from baton import lifecycle
    from baton.config import ConfigError
    from baton.drone.master import HandoverScriptError
    from baton.drone.mobility import MavsdkMobility
    from baton.drone.serve import serve
    from baton.drone.settings import autopilot_gcs_timeout_s, safety_params
    from baton.lifecycle import run_until_signalled
    from baton.rpc.tls import TlsError

    try:
        settings = settings_from_args(args)
    except (ConfigError, HandoverScriptError, TlsError, ValueError) as exc:
        print(f"baton drone: {exc}", file=sys.stderr)
        return 2
    vehicle = MavsdkMobility(
        settings.vehicle_url,
        signing_key=settings.mavlink_key,
        tlog_dir=Path(args.tlog_dir) if args.tlog_dir is not None else None,
        gcs=ground_stations(settings),
        gcs_failsafe_timeout_s=autopilot_gcs_timeout_s(settings.config),
        fence=safety_params(settings.config).fence,
    )
    return lifecycle.run(run_until_signalled(lambda stop: serve(settings, vehicle, stop)))
