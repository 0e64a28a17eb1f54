"""``baton station``: one edge node's station, hosting many missions' controllers."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from baton import lifecycle
from baton.certs.cli import add_renew_flag, add_tls_flags
from baton.controller.cli import add_mission_python, check_mission_python


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Adds ``baton station``."""
    parser = subparsers.add_parser(
        "station",
        help="run an edge node's station: the controller of every mission whose ring holds it",
        description=(
            "Runs one station: on one port and one identity (the controller certificate of "
            "its id), it hosts a controller session per mission an operator starts on it "
            "(Station.StartMission), each with its own log, history file, mission program "
            "and status; ring calls name their mission in the baton-mission metadata."
        ),
    )
    parser.add_argument(
        "--id",
        type=int,
        required=True,
        help="the station's id: its controller id in every mission's ring, and its "
        "certificate controller-ID (baton certs issue DIR controller-ID)",
    )
    parser.add_argument(
        "--address",
        default="0.0.0.0:50070",
        help="HOST:PORT of the station's one port; port 0 picks a free one "
        "(default: 0.0.0.0:50070)",
    )
    parser.add_argument("--address-file", help="write the bound HOST:PORT to this file")
    parser.add_argument(
        "--state-dir",
        type=Path,
        required=True,
        help="folder of the sessions' history files (missions/ID/), removed with each "
        "session a StopMission ends",
    )
    add_mission_python(parser)
    add_tls_flags(parser)
    add_renew_flag(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Checks the certificate and the interpreter, then serves."""
    from baton.certs.renewal import renewing
    from baton.config import TlsConfig
    from baton.rpc.tls import Identity, Tls, TlsError
    from baton.station.app import serve

    tls = TlsConfig(certs=args.certs or Path("certs"), insecure=args.insecure)
    own: Tls | None = None
    try:
        if args.id < 0:
            raise ValueError(f"--id {args.id}: a station id is 0 or more")
        if not tls.insecure:
            tls = TlsConfig(certs=tls.certs.resolve())
            own = Tls.load(tls.certs, Identity.controller(args.id))  # the files are there
        if args.mission_python is not None:
            check_mission_python(args.mission_python)
        args.state_dir.mkdir(parents=True, exist_ok=True)
    except (TlsError, ValueError, OSError) as exc:
        print(f"baton station: {exc}", file=sys.stderr)
        return 2
    main = serve(
        args.id,
        args.address,
        tls,
        args.state_dir.resolve(),
        args.address_file,
        args.mission_python,
    )
    return lifecycle.run(renewing(main, own, args.renew_from))
