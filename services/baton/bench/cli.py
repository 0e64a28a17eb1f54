"""``baton bench``: the paper's Section 5.4 measurements on the local testbed.

    baton bench timeline   [--out DIR] [--speedup 4]        # Figure 5
    baton bench worst-case [--out DIR] [--repeat 3] [--quick]  # Figure 6
    baton bench micro      [--out DIR] [--quick]            # proxy, replay, ring, T_conn
    baton bench failover   [--out DIR] [--kills 10] [--quick]  # kill -9 of the master
    baton bench fleet      [--out DIR] [--missions 1,5,10,25,50] [--quick]  # N per station

Each writes its figures, JSON and a markdown table under --out and prints the
table at the end. See docs/benchmarks.md for the results and their reading.
"""

from __future__ import annotations

import argparse
import asyncio
from pathlib import Path

from baton.config import parse_size


def _size_mb(text: str) -> int:
    try:
        return parse_size(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Adds ``baton bench`` and its three benchmarks."""
    parser = subparsers.add_parser(
        "bench",
        help="benchmarks reproducing the paper's Section 5.4",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    benches = parser.add_subparsers(dest="bench", metavar="BENCH", required=True)

    def common(sub: argparse.ArgumentParser) -> None:
        sub.add_argument(
            "--out", type=Path, default=Path("out/bench"), help="output folder (default: out/bench)"
        )
        sub.add_argument(
            "--quick", action="store_true", help="a reduced, fast variant (for CI and tests)"
        )

    timeline = benches.add_parser(
        "timeline",
        help="Figure 5: request inter-arrival time and log size, 2 controllers, 3 handovers",
    )
    common(timeline)
    timeline.add_argument(
        "--speedup",
        type=float,
        default=None,
        help="sim vehicle and mission clock speed-up (default 4, --quick 20); pictures and "
        "handovers "
        "still cross the emulated links in real time",
    )
    timeline.add_argument(
        "--flush-limit",
        type=_size_mb,
        default=None,
        help="flush limit, e.g. 2MB (default 2MB, as the paper)",
    )
    timeline.set_defaults(run=_run_timeline)

    worst = benches.add_parser(
        "worst-case",
        help="Figure 6: worst-case handover delay vs flush limit, 1/3/5 hops, 6 controllers",
    )
    common(worst)
    worst.add_argument(
        "--repeat", type=int, default=3, help="handovers per (flush limit, hops) point (default 3)"
    )
    worst.add_argument(
        "--flush-limits",
        default="0,1MB,2MB,3MB,4MB",
        help="comma-separated flush limits (default 0,1MB,2MB,3MB,4MB)",
    )
    worst.add_argument("--hops", default="1,3,5", help="comma-separated hop counts (default 1,3,5)")
    worst.add_argument(
        "--controllers",
        type=int,
        default=6,
        help="controllers in the ring (default 6, as the paper; 12 for hops up to 11)",
    )
    worst.add_argument(
        "--forwarding",
        default="store-and-forward,cut-through",
        help="the ring's forwarding modes to measure, in one run (default both: "
        "store-and-forward,cut-through)",
    )
    worst.add_argument(
        "--from-json",
        type=Path,
        help="do not run: recompute the model and the report from a saved worst_case.json",
    )
    worst.set_defaults(run=_run_worst_case)

    micro = benches.add_parser(
        "micro", help="proxy round trip, replay speed, ring throughput, T_conn"
    )
    common(micro)
    micro.set_defaults(run=_run_micro)

    replay = benches.add_parser(
        "replay", help="baton replay's speed: a saved log of --calls requests checked offline"
    )
    replay.add_argument(
        "--out",
        type=Path,
        default=Path("out/bench"),
        help="output folder (default: out/bench)",
    )
    replay.add_argument(
        "--calls", type=int, default=10_000, help="requests in the log (default 10000)"
    )
    replay.add_argument("--passes", type=int, default=5, help="replays, median taken (default 5)")
    replay.set_defaults(run=_run_replay)

    failover = benches.add_parser(
        "failover",
        help="kill -9 of the master at seeded request numbers, 3 and 6 controllers: "
        "detection, catch-up, T_conn against the physical limit",
    )
    common(failover)
    failover.add_argument(
        "--kills", type=int, default=None, help="kills per controller count (default 10)"
    )
    failover.add_argument(
        "--controllers", default=None, help="comma-separated controller counts (default 3,6)"
    )
    failover.add_argument("--seed", type=int, default=None, help="kill points' seed (default 1)")
    failover.set_defaults(run=_run_failover)

    fleet = benches.add_parser(
        "fleet",
        help="one station hosting 1 to 50 missions: its CPU and memory per mission, and the "
        "handover delay and proxy round trip of a mission it hosts against a lone mission's",
    )
    common(fleet)
    fleet.add_argument(
        "--missions",
        type=_missions,
        default=None,
        help="comma-separated, rising mission counts hosted by the measured station "
        "(default 1,5,10,25,50; --quick 1,5)",
    )
    fleet.set_defaults(run=_run_fleet)


def _missions(text: str) -> tuple[int, ...]:
    from baton.bench.fleet import parse_missions

    try:
        return parse_missions(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _run_timeline(args: argparse.Namespace) -> int:
    from baton.bench.timeline import TimelineSettings, run_timeline, table

    settings = TimelineSettings.quick() if args.quick else TimelineSettings()
    settings = settings.with_options(speedup=args.speedup, flush_limit=args.flush_limit)
    result = asyncio.run(run_timeline(settings, args.out))
    print(table(result))
    return 0


def _run_worst_case(args: argparse.Namespace) -> int:
    from baton.bench.worst_case import WorstCaseSettings, report_from_json, run_worst_case, table

    if args.from_json is not None:
        print(table(report_from_json(args.from_json, args.out)["summary"]))
        return 0
    if args.quick:
        settings = WorstCaseSettings.quick()
    else:
        try:
            settings = WorstCaseSettings(
                flush_limits=tuple(_size_mb(s) for s in args.flush_limits.split(",")),
                hops=tuple(int(h) for h in args.hops.split(",")),
                repeat=args.repeat,
                forwarding=tuple(_forwarding_modes(args.forwarding)),
                controllers=args.controllers,
            )
        except ValueError as exc:
            raise SystemExit(f"baton bench worst-case: {exc}") from None
    result = asyncio.run(run_worst_case(settings, args.out))
    print(table(result["summary"]))
    return 0


def _forwarding_modes(text: str) -> list[str]:
    from baton.bench.worst_case import FORWARDING_MODES

    modes = [mode.strip() for mode in text.split(",") if mode.strip()]
    unknown = [mode for mode in modes if mode not in FORWARDING_MODES]
    if unknown or not modes:
        raise SystemExit(
            f"baton bench worst-case: --forwarding {text!r}: expected a comma-separated list "
            f"of {', '.join(FORWARDING_MODES)}"
        )
    return modes


def _run_micro(args: argparse.Namespace) -> int:
    from baton.bench.micro import MicroSettings, run_micro, table

    settings = MicroSettings.quick() if args.quick else MicroSettings()
    result = asyncio.run(run_micro(settings, args.out))
    print(table(result))
    return 0


def _run_failover(args: argparse.Namespace) -> int:
    from baton.bench.failover import FailoverSettings, run_failover, table

    settings = FailoverSettings.quick() if args.quick else FailoverSettings()
    counts = tuple(int(c) for c in args.controllers.split(",")) if args.controllers else None
    if args.kills is not None and args.kills < 1:
        raise SystemExit("baton bench failover: --kills must be >= 1")
    if counts is not None and any(c < 2 for c in counts):
        raise SystemExit("baton bench failover: --controllers must be >= 2 each")
    settings = settings.with_options(kills=args.kills, controllers=counts, seed=args.seed)
    result = asyncio.run(run_failover(settings, args.out))
    print(table(result["summary"], result["takeover_time_s"]))
    return 0 if all(run["ok"] for run in result["runs"]) else 1


def _run_replay(args: argparse.Namespace) -> int:
    from baton.bench.offline_replay import run_replay_bench

    if args.calls < 1 or args.passes < 1:
        print("baton bench replay: --calls and --passes must be >= 1")
        return 2
    result = run_replay_bench(args.out, args.calls, args.passes)
    print(
        f"baton replay: {result['calls']} logged calls checked in {result['median_s']:.3f} s "
        f"(median of {result['passes']}; {result['calls_per_s']:,.0f} calls/s; target "
        f"< {result['target_s']:.1f} s)\nby hand: time {result['command']}"
    )
    return 0 if result["median_s"] < result["target_s"] else 1


def _run_fleet(args: argparse.Namespace) -> int:
    from baton.bench.fleet import FleetSettings, run_fleet_bench, table

    settings = FleetSettings.quick() if args.quick else FleetSettings()
    result = asyncio.run(run_fleet_bench(settings.with_missions(args.missions), args.out))
    print(table(result))
    return 1 if result["stopped"] else 0
