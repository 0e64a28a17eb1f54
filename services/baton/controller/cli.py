"""``baton controller``: one mission controller of the ring."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

from baton import lifecycle
from baton.certs.cli import add_renew_flag, add_tls_flags
from baton.sdk.run import add_mission_arg

# What a --mission-python interpreter must be able to import.
MISSION_RUNNER = "baton.sdk.run"


def add_mission_python(parser: argparse.ArgumentParser) -> None:
    """``--mission-python PATH``: the interpreter that runs the mission program."""
    parser.add_argument(
        "--mission-python",
        metavar="PATH",
        help="the Python that runs the mission program, e.g. a virtualenv's bin/python with "
        "only the SDK in it (pip install ./clients); it runs with -E (no PYTHONPATH); "
        "default: the one running baton",
    )


def check_mission_python(path: str) -> None:
    """Raises ValueError unless ``path`` is a Python that can run a mission program."""
    if not (os.path.isfile(path) and os.access(path, os.X_OK)):
        raise ValueError(f"--mission-python {path}: not an executable file")
    try:
        check = [path, "-E", "-c", f"import {MISSION_RUNNER}"]
        result = subprocess.run(check, capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise ValueError(f"--mission-python {path}: does not run: {exc}") from None
    if result.returncode != 0:
        last = (result.stderr.strip().splitlines() or ["no output"])[-1]
        raise ValueError(
            f"--mission-python {path}: cannot import {MISSION_RUNNER} ({last}); install the "
            "SDK into its environment: pip install ./clients"
        )


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Adds ``baton controller``."""
    parser = subparsers.add_parser(
        "controller",
        help="run a mission controller (Algorithm 1)",
        description=(
            "Runs one mission controller: serves the drone API (Mobility, Camera, Clock) to its "
            "local mission program, logs and circulates the master's replies along the ring, "
            "replays them, and takes over when the drone hands over."
        ),
    )
    parser.add_argument("--id", type=int, required=True, help="this controller's id in the config")
    parser.add_argument(
        "--config", required=True, help="testbed YAML: drone, controllers, ring, flush limit"
    )
    parser.add_argument(
        "--flush-limit",
        help="override the config's flush limit, bytes with units (0, 512KB, 2MB)",
    )
    parser.add_argument(
        "--mission", help="a mission file (defines mission(drone, **params)) to run on start"
    )
    add_mission_arg(parser)
    add_mission_python(parser)
    parser.add_argument(
        "--address-file", help="write the address this controller listens on to this file"
    )
    parser.add_argument(
        "--log-file",
        metavar="FILE",
        help="keep every log message this controller holds in this SQLite file and recover "
        "from it on restart (one mission, one file; format in baton/controller/history.py); "
        "default: a temporary file that goes with the process",
    )
    add_tls_flags(parser)
    add_renew_flag(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Loads and checks the configuration, then serves."""
    from baton.certs.renewal import renewing
    from baton.config import ConfigError, load_config, merge
    from baton.controller.app import serve
    from baton.rpc.tls import Identity, TlsError

    try:
        # --certs: the certificates in that folder, over a file that said insecure.
        secure = False if args.certs is not None and not args.insecure else None
        flags = [
            ("--flush-limit", "flush_limit", args.flush_limit),
            ("--certs", "tls.certs", args.certs),
            ("--certs", "tls.insecure", secure),
            ("--insecure", "tls.insecure", True if args.insecure else None),
        ]
        config = merge(load_config(args.config), flags, args.config)
        config.controller(args.id)
        own = config.tls_for(Identity.controller(args.id))  # the files are there
        if args.mission_python is not None:
            check_mission_python(args.mission_python)
    except (ConfigError, TlsError, ValueError) as exc:
        print(f"baton controller: {exc}", file=sys.stderr)
        return 2
    except KeyError as exc:
        print(f"baton controller: --id {args.id}: {exc.args[0]}", file=sys.stderr)
        return 2
    main = serve(
        config,
        args.id,
        args.mission,
        args.mission_arg,
        args.address_file,
        args.log_file,
        args.mission_python,
    )
    return lifecycle.run(renewing(main, own, args.renew_from))
