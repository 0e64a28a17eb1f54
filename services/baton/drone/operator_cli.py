"""``baton operator pause|resume|abort|land-now``: an operator's commands to the drone
service (Drone.Pause, Resume, Abort, LandNow; docs/operating.md, "Operator commands").

It calls as the operator's certificate (``operator.crt`` of ``--certs``), which the
drone checks; prints what the drone took (when, after which request, what the
vehicle was told and did) and exits 0, or prints the drone's refusal and exits 1.
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

from baton.certs.cli import add_tls_flags, tls_from_flags

if TYPE_CHECKING:
    from baton.rpc.tls import Tls
    from baton.v1 import drone_pb2, drone_pb2_grpc

COMMANDS = ("pause", "resume", "abort", "land-now")
# An operator's call must not hang on a drone out of reach.
CALL_TIMEOUT_S = 10.0


def _address(text: str) -> str:
    from baton.config import parse_address

    try:
        return parse_address(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Adds ``baton operator``."""
    parser = subparsers.add_parser(
        "operator",
        help="an operator's commands to a running mission: pause, resume, abort, land-now",
        description="Pause (the vehicle holds; the mission's next call waits at the drone), "
        "resume (after a pause or a failsafe), abort (the mission ends; the vehicle returns "
        "home, or lands with --land) or land-now (the mission ends; the vehicle lands where "
        "it is). Calls the drone service as the operator's certificate.",
    )
    parser.add_argument("command", choices=COMMANDS, help="what to do")
    parser.add_argument(
        "--config",
        metavar="FILE",
        help="testbed YAML (baton.config): the drone's address and the certificates",
    )
    parser.add_argument(
        "--address",
        type=_address,
        help="the drone service's HOST:PORT (default: the config's drone.address, else "
        "127.0.0.1:50051)",
    )
    action = parser.add_mutually_exclusive_group()
    action.add_argument(
        "--rtl", action="store_true", help="abort: the vehicle returns home (the default)"
    )
    action.add_argument("--land", action="store_true", help="abort: the vehicle lands where it is")
    parser.add_argument("--note", default="", help="why, for the record (GetStatus, the report)")
    add_tls_flags(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Sends the command; 0 if the drone took it, 1 if it refused, 2 for bad flags."""
    import asyncio

    from baton.config import ConfigError, load_config
    from baton.rpc.tls import OPERATOR, TlsError

    if (args.rtl or args.land) and args.command != "abort":
        print("baton operator: --rtl and --land go with abort only", file=sys.stderr)
        return 2
    try:
        config = load_config(args.config) if args.config else None
        tls = tls_from_flags(args, config, OPERATOR)
    except (ConfigError, TlsError, ValueError) as exc:
        print(f"baton operator: {exc}", file=sys.stderr)
        return 2
    address = args.address or (config.drone.address if config else "127.0.0.1:50051")
    return asyncio.run(_send(args, address, tls))


async def _send(args: argparse.Namespace, address: str, tls: Tls | None) -> int:
    import grpc

    from baton.rpc.channels import aio_channel
    from baton.rpc.tls import DRONE
    from baton.v1 import drone_pb2_grpc

    async with aio_channel(address, tls, DRONE if tls is not None else None) as channel:
        stub = drone_pb2_grpc.DroneStub(channel)
        try:
            taken = await send_command(stub, args.command, args.note, args.land)
        except grpc.aio.AioRpcError as exc:
            print(
                f"baton operator {args.command}: refused by the drone at {address}: "
                f"{exc.code().name}: {exc.details()}",
                file=sys.stderr,
            )
            return 1
    print(describe(taken))
    return 0


async def send_command(
    stub: drone_pb2_grpc.DroneAsyncStub, command: str, note: str = "", land: bool = False
) -> drone_pb2.OperatorCommand:
    """The operator's ``command`` (pause, resume, abort: a return, or a landing with
    ``land``; land-now) to the drone, as the drone took it; AioRpcError if it refused."""
    from baton.v1 import drone_pb2

    if command == "pause":
        paused = await stub.Pause(drone_pb2.PauseRequest(note=note), timeout=CALL_TIMEOUT_S)
        return paused.command
    if command == "resume":
        resumed = await stub.Resume(drone_pb2.ResumeRequest(), timeout=CALL_TIMEOUT_S)
        return resumed.command
    if command == "abort":
        request = drone_pb2.AbortRequest(action="land" if land else "rtl", note=note)
        return (await stub.Abort(request, timeout=CALL_TIMEOUT_S)).command
    landing = drone_pb2.LandNowRequest(note=note)
    return (await stub.LandNow(landing, timeout=CALL_TIMEOUT_S)).command


def describe(taken: drone_pb2.OperatorCommand) -> str:
    """One line: the command as the drone took it, and what the vehicle did."""
    import time

    at = time.strftime("%H:%M:%S", time.gmtime(taken.at))
    told = (
        f"; the vehicle told {taken.action}: {taken.vehicle or 'no answer'}" if taken.action else ""
    )
    return f"{at} UTC {taken.command}: {taken.reason}{told}"
