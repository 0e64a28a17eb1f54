"""``baton sim-vehicle``: run one or more simulated multicopters."""

from __future__ import annotations

import argparse
import asyncio
import math
import sys
from pathlib import Path
from typing import Any

from baton import lifecycle
from baton.lifecycle import announce, run_until_signalled, until_stopped

DEFAULT_HOME = "47.397742,8.545594,488.0"  # PX4 SITL's default home (Zurich)


def parse_home(text: str) -> tuple[float, float, float]:
    """``LAT,LON,ALT`` (degrees, degrees, metres AMSL) as a checked tuple."""
    parts = text.split(",")
    try:
        lat, lon, alt = (float(part) for part in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected LAT,LON,ALT like {DEFAULT_HOME!r}, got {text!r}"
        ) from None
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise argparse.ArgumentTypeError(f"latitude/longitude out of range in {text!r}")
    return lat, lon, alt


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0 < value < math.inf:
        raise argparse.ArgumentTypeError(f"must be a number > 0 and finite, got {text!r}")
    return value


def _port(text: str) -> int:
    if not text.isdigit() or not 0 <= int(text) <= 65535:
        raise argparse.ArgumentTypeError(f"must be a port in 0..65535, got {text!r}")
    return int(text)


def _not_negative(text: str) -> float:
    value = float(text)
    if not 0 <= value < math.inf:
        raise argparse.ArgumentTypeError(f"must be >= 0 and finite, got {text!r}")
    return value


def register(subparsers: Any) -> None:
    """Adds the ``sim-vehicle`` subcommand."""
    parser = subparsers.add_parser(
        "sim-vehicle",
        help="a simulated MAVLink multicopter (PX4 dialect) for MAVSDK",
        description=(
            "Runs a simulated multicopter that MAVSDK connects to like PX4 SITL. Like a real "
            "autopilot it streams only HEARTBEAT until asked (MAV_CMD_SET_MESSAGE_INTERVAL, "
            "MAV_CMD_REQUEST_MESSAGE) and arms only after --warmup. "
            "Prints one JSON line {event: listening, url, port} per vehicle on stdout."
        ),
    )
    parser.add_argument(
        "--host", default="127.0.0.1", help="address to bind the UDP port on (default: 127.0.0.1)"
    )
    parser.add_argument(
        "--port",
        type=_port,
        default=0,
        help="UDP port to listen on; 0 (the default) lets the kernel pick a free one",
    )
    parser.add_argument(
        "--home",
        type=parse_home,
        default=parse_home(DEFAULT_HOME),
        help=f"home position LAT,LON,ALT (degrees, degrees, metres AMSL; default {DEFAULT_HOME})",
    )
    parser.add_argument(
        "--system-id",
        type=int,
        default=1,
        help="MAVLink system id of the first vehicle (default 1)",
    )
    parser.add_argument(
        "--count",
        type=int,
        default=1,
        help="how many vehicles to run, each on its own port with the next system id (default 1)",
    )
    parser.add_argument(
        "--speedup",
        type=_positive,
        default=1.0,
        help="simulated time runs this many times faster than wall time, as SITL's speed factor "
        "(default 1)",
    )
    parser.add_argument(
        "--speed",
        type=_positive,
        default=5.0,
        help="default horizontal cruise speed, m/s (default 5; DO_CHANGE_SPEED changes it)",
    )
    parser.add_argument(
        "--max-speed",
        type=_positive,
        default=12.0,
        help="the fastest it flies horizontally, m/s, whatever it is asked; said as PX4's "
        "MPC_XY_VEL_MAX (default 12, PX4's)",
    )
    parser.add_argument(
        "--climb-rate", type=_positive, default=3.0, help="climb and descent rate, m/s (default 3)"
    )
    parser.add_argument(
        "--battery-capacity-wh",
        type=_positive,
        default=100.0,
        help="the battery's energy, Wh (default 100: 24 min at 5 m/s with the default draw)",
    )
    parser.add_argument(
        "--hover-power-w",
        type=_positive,
        default=200.0,
        help="power drawn hovering, W (default 200; a tenth of it armed on the ground)",
    )
    parser.add_argument(
        "--drag-power",
        type=_not_negative,
        default=2.0,
        metavar="W_PER_M2S2",
        help="power drawn beyond hover per (m/s)^2 of ground speed, W (default 2)",
    )
    parser.add_argument(
        "--warmup",
        type=_not_negative,
        default=10.0,
        metavar="SECONDS",
        help="simulated seconds until the estimator is ready, as a real autopilot's (ArduCopter "
        "takes ~40 s): before, no home, GPS unhealthy, arming refused with 'PreArm: ...' "
        "(default 10, 1 s of wall time at --speedup 10; 0 = ready at once)",
    )
    parser.add_argument(
        "--arm-refusals",
        type=int,
        default=0,
        metavar="N",
        help="refuse the first N arms once warmed up with 'Arm: Gyros still settling' and "
        "MAV_RESULT_FAILED, as ArduPilot does when an arming check fails between its pre-arm "
        "reports (default 0)",
    )
    parser.add_argument(
        "--url-file",
        type=Path,
        help="write the MAVLink URL (one line per vehicle) to this file, atomically",
    )
    parser.add_argument(
        "--effects-file",
        type=Path,
        metavar="PATH",
        help="append one JSON line per flight command a vehicle acted on (seq, time, effect: "
        "arm, disarm, takeoff, land, return_to_launch, set_mode, goto with its target, set_speed; "
        "system_id), flushed at once; a retransmission is not counted again; a restarted vehicle "
        "continues the file (default: none written)",
    )
    parser.add_argument(
        "--position-file",
        type=Path,
        metavar="PATH",
        help="keep the vehicle's position in this JSON file, rewritten atomically 20 times a "
        "second, for link emulators with a radio range (baton link --range); one vehicle only",
    )
    parser.add_argument(
        "--mavlink-key",
        type=Path,
        metavar="FILE",
        help="MAVLink 2 signing as ArduPilot does it once it holds a key: accept only frames "
        "signed with this key (RADIO_STATUS excepted), sign every frame sent "
        "(baton certs mavlink-key FILE; default: unsigned)",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Runs the vehicles until SIGTERM or SIGINT; exit code 0."""
    from baton import logs
    from baton.effects import EffectsFile
    from baton.link.radio import POSITION_PERIOD_S, write_position
    from baton.signing import SigningKeyError, read_key
    from baton.sim_vehicle.kinematics import FlightParams, GeoPoint
    from baton.sim_vehicle.server import SimVehicle

    log = logs.get_logger("sim_vehicle")
    try:
        key = read_key(args.mavlink_key) if args.mavlink_key is not None else None
    except SigningKeyError as exc:
        print(f"baton sim-vehicle: --mavlink-key: {exc}", file=sys.stderr)
        return 2
    if args.position_file is not None and args.count != 1:
        print("baton sim-vehicle: --position-file is for one vehicle (--count 1)", file=sys.stderr)
        return 2
    if args.count < 1 or not 1 <= args.system_id <= 256 - args.count:
        log.error("bad --count/--system-id", count=args.count, system_id=args.system_id)
        return 2
    params = FlightParams(
        climb_rate_m_s=args.climb_rate,
        descent_rate_m_s=args.climb_rate,
        cruise_speed_m_s=args.speed,
        max_speed_m_s=args.max_speed,
        warmup_s=args.warmup,
        battery_capacity_wh=args.battery_capacity_wh,
        hover_power_w=args.hover_power_w,
        drag_power_w_per_m2s2=args.drag_power,
        arm_refusals=max(0, args.arm_refusals),
    )
    effects = EffectsFile(args.effects_file)  # one file and sequence for every vehicle

    async def serve(stop: asyncio.Event) -> int:
        vehicles: list[SimVehicle] = []
        try:
            for index in range(args.count):
                vehicle = SimVehicle(
                    GeoPoint(*args.home),
                    system_id=args.system_id + index,
                    host=args.host,
                    port=args.port + index if args.port else 0,
                    speedup=args.speedup,
                    params=params,
                    effects=effects,
                    signing_key=key,
                )
                vehicle.start()
                vehicles.append(vehicle)

            def publish_position() -> None:
                if args.position_file is not None:
                    state = vehicles[0].state()
                    write_position(
                        args.position_file,
                        state.latitude_deg,
                        state.longitude_deg,
                        state.relative_altitude_m,
                    )

            publish_position()  # before the URL file: it is there when the parts start
            listening = []
            for vehicle in vehicles:
                event: dict[str, Any] = {"url": vehicle.url, "port": vehicle.port}
                if args.count > 1:
                    event["system_id"] = vehicle.system_id
                listening.append(event)
            announce(args.url_file, [v.url for v in vehicles], *listening)
            # Wake up now and then anyway: a SIGTERM the kernel hands to a vehicle
            # thread once left a main thread blocked in a lock (a sim vehicle
            # outliving a SIGKILLed testbed).
            period = POSITION_PERIOD_S if args.position_file is not None else 0.2
            await until_stopped(stop, period, publish_position)
            log.info("signalled, stopping")
        finally:
            for vehicle in vehicles:
                vehicle.stop()
        sys.stdout.flush()
        return 0

    return lifecycle.run(run_until_signalled(serve))
