"""``baton bench worst-case``: the paper's Figure 6, handover delay vs flush limit and hops.

Six controllers in a ring, links of 20 ms / 25 Mbit/s between them. For each
forwarding mode and flush limit one run of the bench mission, whose script
(``script.py``) makes the master flush a log of about f + e and has the drone
hand over right after, over 1, 3 and 5 hops, ``repeat`` times each. The
measured delay (the drone's decision to the new master's first request) is
set beside the paper's model T_log(0) + h * T_log(f + e) + T_conn and the
physical limit l + 8 (f + e) / b + T_conn (the bytes the new master lacked,
over one link), with T_conn measured in the same run, and beside them how
busy the machine's cores were meanwhile (``cpu.py``). The paper's
store-and-forward and baton's cut-through run in one invocation, so that
their ratio is measured under the same load.
"""

from __future__ import annotations

import json
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc

from baton.bench.cpu import CpuSampler
from baton.bench.model import MB, master_log_sizes, t_log, t_max
from baton.bench.runner import (
    audit_calls,
    machine,
    markdown_table,
    run_plan,
    say,
    write_json,
)
from baton.bench.script import (
    BENCH_MISSION,
    TAKE_PICTURE,
    bench_mission_args,
    entry_bytes,
    worst_case_script,
)
from baton.config import LinkSpec
from baton.testbed.local import (
    PAPER_CONTROLLER_LINK,
    WIFI_DRONE_LINK,
    Snapshot,
    TestbedPlan,
    local_config,
)
from baton.v1 import ring_pb2

CONTROLLERS = 6
# The paper's protocol first, then baton's.
FORWARDING_MODES = ("store-and-forward", "cut-through")


@dataclass(frozen=True)
class WorstCaseSettings:
    """What to measure."""

    flush_limits: tuple[int, ...] = (0, MB, 2 * MB, 3 * MB, 4 * MB)
    hops: tuple[int, ...] = (1, 3, 5)
    repeat: int = 3
    controller_link: LinkSpec = PAPER_CONTROLLER_LINK
    drone_link: LinkSpec = WIFI_DRONE_LINK
    # The ring's forwarding modes to measure (RingConfig.forwarding), in this order.
    forwarding: tuple[str, ...] = FORWARDING_MODES
    controllers: int = CONTROLLERS

    def __post_init__(self) -> None:
        if not 2 <= self.controllers <= 16:
            raise ValueError(f"controllers must be 2..16, got {self.controllers}")
        far = [h for h in self.hops if not 0 < h < self.controllers]
        if far:
            raise ValueError(
                f"hops {far} do not fit a ring of {self.controllers} controllers: "
                f"use 1..{self.controllers - 1}"
            )

    @classmethod
    def quick(cls) -> WorstCaseSettings:
        """The reduced set for CI: flush 1 MB, 1 and 3 hops, once, in both modes."""
        return cls(flush_limits=(MB,), hops=(1, 3), repeat=1)


def settle_seconds(
    flush_limit: int, largest_entry: int, link: LinkSpec, controllers: int = CONTROLLERS
) -> float:
    """Time for a log of f + e to go once round the ring, with room for replay and contention."""
    once = t_log(flush_limit + largest_entry, link.latency, link.bandwidth)
    return round(1.3 * (controllers - 1) * once + 1.0, 1)


async def measure_flush_limit(
    flush_limit: int, forwarding: str, settings: WorstCaseSettings, workdir: Path
) -> dict[str, Any]:
    """One run at ``flush_limit`` with ``forwarding``: every hop count ``repeat`` times."""
    full_picture = entry_bytes_of_full_picture()
    settle = settle_seconds(
        flush_limit, full_picture, settings.controller_link, settings.controllers
    )
    hop_sequence = [h for _ in range(settings.repeat) for h in settings.hops]
    script = worst_case_script(flush_limit, hop_sequence, settings.controllers, settle)
    plan = TestbedPlan(
        config=local_config(
            settings.controllers,
            flush_limit=flush_limit,
            ring={"forwarding": forwarding},
            speedup=1.0,
            controller_link=settings.controller_link,
            drone_link=settings.drone_link,
        ),
        handovers=script.handovers,
        mission_args=bench_mission_args(script.script),
        mission_file=BENCH_MISSION,
    )
    timeout = 120 + len(hop_sequence) * (settle + 4 * t_log(flush_limit + full_picture, 0, 20e6))
    label = f"worst-case {forwarding} f={flush_limit / MB:g} MB"
    rundir = workdir / f"{forwarding}-flush-{flush_limit}"
    with CpuSampler() as cpu:
        snapshot = await run_plan(plan, rundir, timeout, label)

    requests = {c.reqnr: c.request_bytes for c in script.calls}
    calls = audit_calls(snapshot, requests, {c.reqnr: c.method for c in script.calls})
    if len(calls) != len(script.calls):
        raise RuntimeError(
            f"{label}: the drone served {len(calls)} requests, the script has "
            f"{len(script.calls)}; was the bench mission given its script?"
        )
    actual = {
        p.reqnr: p
        for p in master_log_sizes(calls, flush_limit, [p.after_reqnr for p in script.points])
    }
    largest = max(entry_bytes(c) for c in calls if c.method == TAKE_PICTURE)
    records = {h.after_reqnr: h for h in snapshot.drone.handovers}
    # The initial master's first connection is part of the testbed's start,
    # not of a handover; T_conn in the model is the mean of the others.
    startup, *handover_t_conn = snapshot.controllers[0].t_conn_s
    others = [t for cid, c in snapshot.controllers.items() if cid != 0 for t in c.t_conn_s]
    handed_over = handover_log_bytes(snapshot)
    points: list[dict[str, Any]] = []
    for p in script.points:
        flushed = actual[p.picture_reqnr].flushed if p.picture_reqnr in actual else 0
        # What the old master really held when it handed over: right after
        # its largest flush, at most a small entry or two.
        held = handed_over.get(p.after_reqnr, -1)
        record = records.get(p.after_reqnr)
        points.append(
            {
                "forwarding": forwarding,
                "flush_limit": flush_limit,
                "hops": p.hops,
                "after_reqnr": p.after_reqnr,
                "old_master": p.old_master,
                "new_master": p.new_master,
                "flushed_bytes": flushed,
                "handover_log_bytes": held,
                "placed_after_flush": flushed >= flush_limit and flushed > 0 and 0 <= held < 4096,
                "delay_s": record.delay_s if record is not None else 0.0,
                # How busy the machine's cores were from the decision to the first
                # request: the contention the delay beyond the limit includes.
                "cores_busy": (
                    cpu.busy(record.decided_at, record.first_request_at)
                    if record is not None
                    else None
                ),
            }
        )
    run = {
        "forwarding": forwarding,
        "flush_limit": flush_limit,
        "largest_entry_bytes": largest,
        "t_conn_startup_s": startup,
        "t_conn_samples_s": handover_t_conn + others,
        "settle_s": settle,
        "requests": len(calls),
        "points": points,
    }
    apply_model(run, settings)
    for point in points:
        say(
            f"{label}: {point['hops']} hop(s) {point['old_master']}->{point['new_master']} "
            f"after reqnr {point['after_reqnr']}: flushed {point['flushed_bytes'] / MB:.2f} MB, "
            f"delay {point['delay_s'] * 1e3:.0f} ms, model {point['model_s'] * 1e3:.0f} ms, "
            f"limit {point['limit_s'] * 1e3:.0f} ms"
        )
    return run


async def _measure_with_retry(
    flush_limit: int, forwarding: str, settings: WorstCaseSettings, workdir: Path
) -> dict[str, Any]:
    """One flush limit; a run that fails (a status call timing out under load) runs once more."""
    try:
        return await measure_flush_limit(flush_limit, forwarding, settings, workdir)
    except (RuntimeError, TimeoutError, grpc.RpcError) as exc:
        say(
            f"worst-case {forwarding} f={flush_limit / MB:g} MB: run failed ({exc!r:.200}); "
            "running it again"
        )
        return await measure_flush_limit(flush_limit, forwarding, settings, workdir / "retry")


def handover_log_bytes(snapshot: Snapshot) -> dict[int, int]:
    """The old master's log size at each handover, by the drone's after-reqnr (the old
    masters' status)."""
    return {
        h.drone_after_reqnr: h.log_bytes
        for c in snapshot.controllers.values()
        for h in c.handovers
        if h.role == ring_pb2.HANDOVER_ROLE_OLD
    }


def apply_model(run: dict[str, Any], settings: WorstCaseSettings) -> None:
    """Adds the paper's model (and the extended one) to every point of ``run``."""
    samples = run["t_conn_samples_s"]
    t_conn_s = statistics.fmean(samples) if samples else 0.0
    run["t_conn_s"] = t_conn_s
    link = settings.controller_link
    bandwidth = link.bandwidth  # None: unlimited (the model's transfer takes no time)
    for point in run["points"]:
        point["model_s"] = t_max(
            run["flush_limit"],
            run["largest_entry_bytes"],
            point["hops"],
            t_conn_s,
            link.latency,
            bandwidth,
        )
        # Known terms the paper leaves out: the notice and the first request
        # each cross the drone link once, and the flushed log was f + e as
        # actually logged rather than as nominal sizes.
        point["extended_model_s"] = (
            t_log(0, link.latency, bandwidth)
            + point["hops"] * t_log(point["flushed_bytes"], link.latency, bandwidth)
            + t_conn_s
            + 2 * settings.drone_link.latency
        )
        # The physical limit: what the new master lacked (the flushed log and the
        # handover message) over one link, then the connection.
        lacked = point["flushed_bytes"] + max(point["handover_log_bytes"], 0)
        point["limit_s"] = t_log(lacked, link.latency, bandwidth) + t_conn_s


def forwarding_of(run: dict[str, Any]) -> str:
    """A run's forwarding mode (a file saved before there were two: the paper's)."""
    return str(run.get("forwarding", "store-and-forward"))


def entry_bytes_of_full_picture() -> int:
    """The predicted log entry of one picture at the default resolution (the paper's e)."""
    from baton.bench.script import ScriptBuilder

    return entry_bytes(ScriptBuilder().picture())


def summarize(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (flush limit, hops): measured mean/min/max, model, ratio."""
    rows = []
    order = {mode: k for k, mode in enumerate(FORWARDING_MODES)}
    for run in sorted(runs, key=lambda r: (order[forwarding_of(r)], r["flush_limit"])):
        by_hops: dict[int, list[dict[str, Any]]] = {}
        for point in run["points"]:
            by_hops.setdefault(point["hops"], []).append(point)
        for hops, points in sorted(by_hops.items()):
            delays = [p["delay_s"] for p in points]
            mean = statistics.fmean(delays)
            model = points[0]["model_s"]
            extended = statistics.fmean(p["extended_model_s"] for p in points)
            limit = statistics.fmean(p["limit_s"] for p in points)
            busy = [p["cores_busy"] for p in points if p.get("cores_busy") is not None]
            rows.append(
                {
                    "forwarding": forwarding_of(run),
                    "flush_limit": run["flush_limit"],
                    "hops": hops,
                    "n": len(delays),
                    "mean_s": mean,
                    "min_s": min(delays),
                    "max_s": max(delays),
                    "model_s": model,
                    "ratio": mean / model if model > 0 else float("nan"),
                    "extended_model_s": extended,
                    "extended_ratio": mean / extended if extended > 0 else float("nan"),
                    "limit_s": limit,
                    "limit_ratio": mean / limit if limit > 0 else float("nan"),
                    "all_placed_after_flush": all(p["placed_after_flush"] for p in points),
                    "cores_busy": statistics.fmean(busy) if busy else None,
                }
            )
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    """The summary as a markdown table."""
    return markdown_table(
        [
            "forwarding",
            "flush (MB)",
            "hops",
            "n",
            "mean (ms)",
            "min (ms)",
            "max (ms)",
            "model (ms)",
            "ratio",
            "extended model (ms)",
            "ratio to extended",
            "physical limit (ms)",
            "ratio to limit",
            "cores busy",
        ],
        [
            [
                r["forwarding"],
                f"{r['flush_limit'] / MB:g}",
                r["hops"],
                r["n"],
                f"{r['mean_s'] * 1e3:.0f}",
                f"{r['min_s'] * 1e3:.0f}",
                f"{r['max_s'] * 1e3:.0f}",
                f"{r['model_s'] * 1e3:.0f}",
                f"{r['ratio']:.2f}",
                f"{r['extended_model_s'] * 1e3:.0f}",
                f"{r['extended_ratio']:.2f}",
                f"{r['limit_s'] * 1e3:.0f}",
                f"{r['limit_ratio']:.2f}",
                "-" if r.get("cores_busy") is None else f"{r['cores_busy']:.0%}",
            ]
            for r in rows
        ],
    )


async def run_worst_case(settings: WorstCaseSettings, out: Path) -> dict[str, Any]:
    """Measures every flush limit, writes worst_case.{json,md,png} under ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    runs = []
    for forwarding in settings.forwarding:
        for flush_limit in settings.flush_limits:
            runs.append(
                await _measure_with_retry(
                    flush_limit, forwarding, settings, out / "worst-case-runs"
                )
            )
    return write_report(runs, settings, out)


def write_report(
    runs: list[dict[str, Any]], settings: WorstCaseSettings, out: Path
) -> dict[str, Any]:
    """Writes worst_case.{json,md,png} from measured runs."""
    from baton.bench.plots import plot_worst_case

    rows = summarize(runs)
    result = {
        "settings": {
            "controllers": settings.controllers,
            "flush_limits": list(settings.flush_limits),
            "hops": list(settings.hops),
            "repeat": settings.repeat,
            "forwarding": list(settings.forwarding),
            "controller_link": settings.controller_link.model_dump(),
            "drone_link": settings.drone_link.model_dump(),
        },
        "machine": machine(),
        "runs": runs,
        "summary": rows,
    }
    write_json(out / "worst_case.json", result)
    (out / "worst_case.md").write_text(table(rows))
    plot_worst_case(rows, out / "worst_case.png", settings.controllers)
    return result


def report_from_json(path: Path, out: Path) -> dict[str, Any]:
    """Recomputes the model and the report of a saved ``worst_case.json`` without running.

    A file saved before ``t_conn_startup_s`` existed has the initial master's
    start-up connection as its first T_conn sample; it is set apart here.
    """
    saved = json.loads(path.read_text())
    options = saved["settings"]
    settings = WorstCaseSettings(
        flush_limits=tuple(options["flush_limits"]),
        hops=tuple(options["hops"]),
        repeat=options["repeat"],
        forwarding=tuple(options.get("forwarding", ["store-and-forward"])),
        controllers=options.get("controllers", CONTROLLERS),
        controller_link=LinkSpec(**options["controller_link"]),
        drone_link=LinkSpec(**options["drone_link"]),
    )
    for run in saved["runs"]:
        if "t_conn_startup_s" not in run:
            run["t_conn_startup_s"], *run["t_conn_samples_s"] = run["t_conn_samples_s"]
        apply_model(run, settings)
    out.mkdir(parents=True, exist_ok=True)
    return write_report(saved["runs"], settings, out)
