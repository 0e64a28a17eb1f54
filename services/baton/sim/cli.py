"""``python -m baton.sim``: run one seed (and replay it exactly), or a range of seeds.

    .venv/bin/python -m baton.sim --seed 1234        # one seed and what the oracles say
    .venv/bin/python -m baton.sim --seeds 0-99999    # many, on every core; a replay line each
    .venv/bin/python -m baton.sim --seed 7 --mutation line44 --trace   # every event

Exit status 1 if any seed failed.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import sys
import time
from collections.abc import Sequence
from functools import partial

from baton.drone.policy import POLICIES
from baton.sim.findings import FINDINGS, STILL_ALLOWED
from baton.sim.mutations import MUTATIONS, mutated
from baton.sim.world import SimOptions, run_seed, run_seeds


def _range(text: str) -> range:
    first, _, last = text.partition("-")
    return range(int(first), int(last or first) + 1)


def _calls(text: str) -> tuple[int, int]:
    first, _, last = text.partition("-")
    return int(first), int(last or first)


def _findings(text: str) -> frozenset[str]:
    codes = frozenset(code.strip().upper() for code in text.split(",") if code.strip())
    known = set(FINDINGS) | STILL_ALLOWED
    unknown = codes - known
    if unknown:
        raise argparse.ArgumentTypeError(
            f"unknown finding {', '.join(sorted(unknown))}; known: {', '.join(sorted(known))}"
        )
    return codes


def _counts(counts: dict[str, int]) -> str:
    return ", ".join(f"{what} {n}" for what, n in sorted(counts.items())) or "none"


def parser() -> argparse.ArgumentParser:
    """The command line."""
    p = argparse.ArgumentParser(
        prog="python -m baton.sim", description="baton's deterministic simulation (issue 9)"
    )
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--seed", type=int, help="run this seed and show what it did")
    which.add_argument("--seeds", type=_range, help="run a range of seeds, e.g. 0-99999")
    p.add_argument("--calls", type=_calls, default=None, help="mission length range, e.g. 8-24")
    p.add_argument(
        "--kill-master",
        action="store_true",
        help="let kills (restarted later) hit a master in any sense",
    )
    p.add_argument(
        "--lose-master",
        action="store_true",
        help="issue 10: lose the master for good (mid-flush, right after a handover, any "
        "time) or cut its drone link for a while",
    )
    p.add_argument(
        "--prepared",
        action="store_true",
        help="make every scripted handover and Handover call a prepared one (the default "
        "mix prepares a quarter of the script's lines; --lose-master none)",
    )
    p.add_argument(
        "--policy",
        choices=POLICIES[1:],
        default=None,
        help="fly the vehicle along a corridor of stations with radio range and let the "
        "drone's handover policy move the master by prepared handovers",
    )
    p.add_argument(
        "--stall-new-master",
        action="store_true",
        help="cut the ring from a new master right after a cooperative switch, for about "
        "as long as the drone lets a master go without serving (its drone link stays up)",
    )
    p.add_argument(
        "--failsafe",
        action="store_true",
        help="issue 32: the drone's lost-link failsafe on; every station cut from the drone "
        "at a drawn moment, in most seeds for longer than lost_link, and an operator's "
        "Resume in half of them",
    )
    p.add_argument(
        "--operator",
        action="store_true",
        help="issue 32: an operator's commands at a drawn moment: a pause then a resume "
        "(or an abort), an abort (rtl or land), or a land-now",
    )
    p.add_argument(
        "--lying",
        action="store_true",
        help="issue 33: every part signs and checks with its key, and one station forges "
        "frames (newer masterships, invented or altered replies, replays) at drawn moments",
    )
    p.add_argument(
        "--autopilot",
        action="store_true",
        help="issue 32: the autopilot takes the vehicle over at a drawn moment (a return, "
        "a landing or a pilot's mode the drone did not command), and an operator's Resume "
        "in half the seeds",
    )
    p.add_argument(
        "--takeover-after",
        type=float,
        default=None,
        help="the drone's takeover and the ring's detection time in seconds (default: 3, "
        "or drawn with --lose-master)",
    )
    p.add_argument(
        "--allow",
        type=_findings,
        default=frozenset(),
        help="let in the scenarios of known findings, e.g. F1,F4 (see baton.sim.findings)",
    )
    p.add_argument("--mutation", choices=sorted(MUTATIONS), help="put a known defect back")
    p.add_argument("--trace", action="store_true", help="print every event of --seed")
    p.add_argument(
        "--check-every",
        type=int,
        default=SimOptions().check_every,
        help="check the invariants (baton.sim.invariants) after every N events (0: never)",
    )
    p.add_argument("--stop-at-first", action="store_true", help="with --seeds: stop at a failure")
    p.add_argument(
        "--workers",
        type=int,
        default=os.cpu_count() or 1,
        help="with --seeds: processes to run them in (default: one per core)",
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Runs what the command line asks; 1 if a seed failed."""
    args = parser().parse_args(argv)
    default = SimOptions()
    low, high = args.calls or (default.min_calls, default.max_calls)
    options = SimOptions(
        min_calls=low,
        max_calls=high,
        kill_master=args.kill_master,
        lose_master=args.lose_master,
        prepared=args.prepared,
        policy=args.policy,
        stall_new_master=args.stall_new_master,
        failsafe=args.failsafe,
        operator=args.operator,
        lying=args.lying,
        autopilot=args.autopilot,
        takeover_after=args.takeover_after,
        allow=args.allow,
        mutation=args.mutation,
        trace=args.trace and args.seed is not None,
        check_every=args.check_every,
    )
    if args.seed is not None:
        with mutated(args.mutation):
            outcome = run_seed(args.seed, options)
        if args.trace:
            print("\n".join(outcome.trace))
        if outcome.ok:
            print(f"seed {args.seed}: ok\n  {outcome.summary}\n  faults: {outcome.faults}")
        else:
            print(outcome.report())
        if outcome.prepared["begun"]:
            p = outcome.prepared
            print(
                f"  prepared handovers: {p['begun']} begun, {p['prepared']} carried out, "
                f"{p['forced']} forced at the timeout; the word understated what the target "
                f"lacked {p['understated']} times"
            )
        if outcome.policy_decided or outcome.policy_switches:
            print(
                f"  policy steps: {_counts(outcome.policy_decided)}; its handovers ended: "
                f"{_counts(outcome.policy_switches)}"
            )
        print(f"  {outcome.events} events, {outcome.virtual_s:.1f} s virtual, {outcome.digest}")
        return 0 if outcome.ok else 1
    seeds: range = args.seeds
    chunk = 200
    parts = [seeds[i : i + chunk] for i in range(0, len(seeds), chunk)]
    failed = known = 0
    started = time.perf_counter()
    # spawn: workers import baton afresh and apply the mutation themselves.
    context = multiprocessing.get_context("spawn")
    with context.Pool(args.workers) as pool:
        for outcomes in pool.imap(partial(run_seeds, options=options), parts):
            for outcome in outcomes:
                if outcome.failed:
                    failed += 1
                    print(outcome.report(), flush=True)
                else:
                    known += 1
                    print(
                        f"seed {outcome.seed}: known finding {', '.join(outcome.known)} "
                        f"({outcome.replay})",
                        flush=True,
                    )
            if failed and args.stop_at_first:
                pool.terminate()
                break
    elapsed = time.perf_counter() - started
    print(
        f"{len(seeds)} seeds, {failed} failed, {known} struck by known findings, "
        f"{elapsed:.1f} s ({len(seeds) / elapsed:.0f} seeds/s, {args.workers} workers)",
        file=sys.stderr,
    )
    return 1 if failed else 0
