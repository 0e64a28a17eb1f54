"""``baton replay``: check a mission program against saved mission logs, offline."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from baton.sdk.run import add_mission_arg

# Exit codes: every log replayed clean; a divergence; a log or mission that could not be read.
CLEAN, DIVERGED, BAD_INPUT = 0, 1, 2


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Adds ``baton replay``."""
    parser = subparsers.add_parser(
        "replay",
        help="replay saved mission logs against a mission program, offline",
        description=(
            "Replays each saved mission log (a controller's --log-file; the testbed keeps one "
            "per controller in its workdir and names them in its report) against the mission "
            "program, as a replica's REPLAY does, with no drone and no ring. Reports each log "
            "as clean, or its first divergence: the request number, the logged request and "
            "the program's, as protobuf text. Exits 0 if every log replays clean, 1 at a "
            "divergence, 2 for a log or mission that cannot be read."
        ),
    )
    parser.add_argument(
        "logs",
        nargs="+",
        metavar="LOG",
        help="a log file, or a folder: every log file in it and below (*.sqlite) is replayed "
        "(a testbed's workdir holds one per controller; other databases there are skipped)",
    )
    parser.add_argument(
        "--mission",
        required=True,
        help="the mission file (defines mission(drone, **params)), as edited now",
    )
    add_mission_arg(
        parser, "a parameter of the mission function, as the logged run had it; repeatable"
    )
    parser.add_argument(
        "--show-output",
        action="store_true",
        help="print what the program printed (by default only for a log that diverged)",
    )
    parser.set_defaults(run=run)


def log_files(paths: list[str]) -> list[tuple[Path, bool]]:
    """The log files the arguments name, each with whether it was found in a folder;
    ValueError names an argument that names none."""
    files: list[tuple[Path, bool]] = []
    for text in paths:
        path = Path(text)
        if path.is_dir():
            found = sorted(path.rglob("*.sqlite"))
            if not found:
                raise ValueError(f"{path}: a folder with no log file (*.sqlite) in it")
            files += [(file, True) for file in found]
        elif path.is_file():
            files.append((path, False))
        else:
            raise ValueError(f"{path}: no such file or folder")
    return files


def run(args: argparse.Namespace) -> int:
    """Replays every log; prints one verdict a log and a closing count."""
    from baton.controller.history import NotALogFile, OtherDatabase
    from baton.replay.replayer import InconsistentLog, replay_log

    try:
        files = log_files(args.logs)
    except ValueError as exc:
        print(f"baton replay: {exc}", file=sys.stderr)
        return BAD_INPUT
    if not Path(args.mission).is_file():
        print(f"baton replay: --mission {args.mission}: no such file", file=sys.stderr)
        return BAD_INPUT
    clean = diverged = unreadable = 0
    for path, in_folder in files:
        try:
            outcome = replay_log(path, args.mission, args.mission_arg)
        except OtherDatabase as exc:
            if not in_folder:
                unreadable += 1
                print(f"ERROR {path}: {exc}", flush=True)
            else:
                print(f"skip  {path}: not a controller log (another kind of database)")
            continue
        except (NotALogFile, InconsistentLog) as exc:
            unreadable += 1
            print(f"ERROR {path}: {exc}", flush=True)
            continue
        except SystemExit as exc:  # the mission file or its parameters (baton.sdk.run)
            print(f"baton replay: {exc}", file=sys.stderr)
            return BAD_INPUT
        if outcome.clean:
            clean += 1
            ended = f"; the program raised {outcome.program_error}" * bool(outcome.program_error)
            print(
                f"ok    {path}: {outcome.replayed} requests replayed clean in "
                f"{outcome.seconds:.3f} s{ended}",
                flush=True,
            )
        else:
            diverged += 1
            assert outcome.divergence is not None
            print(f"FAIL  {path}: replayed {outcome.replayed} of {outcome.logged} requests, then")
            for line in outcome.divergence.lines():
                print(f"      {line}")
        if outcome.output and (args.show_output or not outcome.clean):
            print("      the program printed:")
            for line in outcome.output.splitlines()[-20:]:
                print(f"      | {line}")
        sys.stdout.flush()
    print(f"{clean} clean, {diverged} diverged, {unreadable} unreadable", flush=True)
    if unreadable or not clean + diverged:
        if not clean + diverged + unreadable:
            print("baton replay: no controller log among those files", file=sys.stderr)
        return BAD_INPUT
    return DIVERGED if diverged else CLEAN
