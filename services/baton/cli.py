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

# Subcommand modules by program name, in the order `baton --help` lists them (a
# module may register more than one program).
PROGRAMS = {
    "sim-vehicle": "baton.sim_vehicle.cli",
    "sitl": "baton.sitl.cli",
    "drone": "baton.drone.cli",
    "operator": "baton.drone.operator_cli",
    "controller": "baton.controller.cli",
    "station": "baton.station.cli",
    "link": "baton.link.cli",
    "radio-netem": "baton.link.cli",
    "testbed": "baton.testbed.cli",
    "fleet": "baton.fleet.cli",
    "replay": "baton.replay.cli",
    "bench": "baton.bench.cli",
    "certs": "baton.certs.cli",
}

# baton's own options that take a value (the program's name is the first word after them).
_VALUED_OPTIONS = ("--log-level", "--die-with-parent")


def program_named(argv: list[str]) -> str | None:
    """The program ``argv`` runs, if it names one of ``PROGRAMS`` (None: ``--help``, a
    typo, or nothing, for which every program is loaded to list or refuse it)."""
    words = iter(argv)
    for word in words:
        if word in _VALUED_OPTIONS:
            next(words, None)
        elif not word.startswith("-"):
            return word if word in PROGRAMS else None
    return None


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser of ``baton`` with every subcommand, or with program ``only``: a part
    the testbed starts loads its own program's modules, not the other eleven (a
    fifth of a second of imports each time); SystemExit naming one that does not load."""
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
    for name in [PROGRAMS[only]] if only is not None else dict.fromkeys(PROGRAMS.values()):
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

    words = sys.argv[1:] if argv is None else argv
    parser = build_parser(program_named(words))
    args = parser.parse_args(words)
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
