"""The ``baton`` command: one subcommand a program.

Each program has a ``cli`` module with ``register(subparsers)``, which adds
its parser (every option with its help) and sets ``run(args) -> int``. Heavy
imports (MAVSDK, matplotlib) happen inside ``run``, so ``--help`` is fast.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

# Before anything imports grpc, which reads it once: gRPC's fork handlers off.
# uvloop starts a process (a controller's mission program, the testbed's parts)
# with fork(); those handlers then run in the child and, when another thread is
# inside gRPC, leave it to die of SIGSEGV or SIGABRT before its exec. baton never
# uses gRPC in a forked child: it always execs. docs/design.md, "Starting
# processes beside gRPC". A value the environment sets is kept.
os.environ.setdefault("GRPC_ENABLE_FORK_SUPPORT", "0")

# Subcommand modules, in the order `baton --help` lists them.
PROGRAMS = [
    "baton.sim_vehicle.cli",
    "baton.sitl.cli",
    "baton.drone.cli",
    "baton.drone.operator_cli",
    "baton.controller.cli",
    "baton.station.cli",
    "baton.link.cli",
    "baton.testbed.cli",
    "baton.fleet.cli",
    "baton.replay.cli",
    "baton.bench.cli",
    "baton.certs.cli",
]


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``baton`` with every subcommand; SystemExit naming one that does not load."""
    parser = argparse.ArgumentParser(
        prog="baton",
        description="Transparent handover of automated drone missions between edge controllers.",
    )
    parser.add_argument(
        "--log-level",
        default="info",
        choices=["debug", "info", "warning", "error"],
        help="structured (JSON) log level on stderr (default: info)",
    )
    parser.add_argument(
        "--die-with-parent",
        type=int,
        metavar="PID",
        help="exit when the parent process PID dies (the testbed starts its parts this way)",
    )
    subparsers = parser.add_subparsers(dest="program", metavar="PROGRAM", required=True)
    for name in PROGRAMS:
        try:
            module = importlib.import_module(name)
        except ImportError as exc:
            # Every program ships with baton: one that does not load is a broken
            # install, said as such, never a subcommand silently missing.
            raise SystemExit(
                f"baton: the subcommand module {name} cannot be imported ({exc}): "
                "the installation is broken; reinstall baton (make install, or "
                "pip install -e '.[dev]')"
            ) from exc
        module.register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``baton`` console script."""
    from baton import logs
    from baton.lifecycle import die_with_parent

    parser = build_parser()
    args = parser.parse_args(argv)
    if args.die_with_parent is not None:
        die_with_parent(args.die_with_parent)
    logs.configure(args.log_level)
    try:
        return int(args.run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except OSError as exc:  # a port in use, an unreadable file: say so, no traceback
        print(f"baton {args.program}: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
