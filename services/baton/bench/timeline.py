"""``baton bench timeline``: the paper's Figure 5 on the local testbed.

The grid mission (5x5 waypoints, 1 s polls, a picture at each waypoint) with
two controllers and a 2 MB flush limit. A dry run without handovers gives the
request sequence; the master's log after every request is computed offline
from it (``model.master_log_sizes``), and three handovers are placed in the
core of the mission where the log holds about 0, 1 and 2 MB. The measured run
then has the drone hand over at those request numbers. The figure shows the
inter-arrival time of requests at the drone and the master's log size over
the request number, with the handovers as dashed lines. A last run makes the
same three handovers as baton's prepared handovers on its cut-through ring
(docs/design.md, "Prepared handover"), so that the paper's and baton's pauses
are measured side by side.
"""

from __future__ import annotations

import csv
import math
import statistics
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, BinaryIO

from baton.bench.model import (
    MB,
    Call,
    LogPoint,
    master_log_sizes,
    pick_in_stretch,
    preparation_limit,
    t_log,
)
from baton.bench.runner import audit_calls, machine, markdown_table, run_plan, say, write_json
from baton.bench.script import GET_POSITION, TAKE_PICTURE
from baton.rpc.labels import label
from baton.rpc.methods import path
from baton.testbed.local import MissionPlan, Snapshot, TestbedPlan, local_config
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2

_FULL = 123.456789
# Request sizes of the grid mission's calls that carry arguments (the rest are empty).
REQUEST_BYTES = {
    path("Mobility.Goto"): api.GotoRequest(
        latitude_deg=_FULL, longitude_deg=_FULL, relative_altitude_m=_FULL
    ).ByteSize(),
    path("Mobility.Takeoff"): api.TakeoffRequest(altitude_m=_FULL).ByteSize(),
    path("Mobility.SetSpeed"): api.SetSpeedRequest(speed_m_s=_FULL).ByteSize(),
}


@dataclass(frozen=True)
class TimelineSettings:
    """What to run."""

    mission: MissionPlan = field(default_factory=MissionPlan)
    flush_limit: int = 2 * MB
    # Speed-up 4: a 50 m leg still takes 2.5 s of real time, long enough for a
    # flushed log of f + e (about 1 s over 25 Mbit/s) to arrive before the
    # handover placed at an "empty" log; at 10 it would still be in flight.
    speedup: float = 4.0
    # 640x540 pixels: a picture of 0.99 MB, so two pictures stay under 2 MB and
    # the log reaches about 2 MB before the third one flushes it (at f + e),
    # as in the paper's figure. The default 640x546 is 1 MiB less a few bytes
    # of log-entry overhead, and two of them plus a few polls cross 2 MB.
    resolution: str = "640x540"
    targets: tuple[float, ...] = (0.0, 1.0 * MB, 2.0 * MB)
    controllers: int = 2
    tolerance: float = 0.15 * MB  # how near a target the log must be at a handover
    attempts: int = 3  # measured runs at most, re-placing handovers that missed
    # The prepared run's prepare_timeout (None: the default, 10 s).
    prepare_timeout_s: float | None = None

    @classmethod
    def quick(cls) -> TimelineSettings:
        """A 3x3 grid, 20 m apart, at speed-up 20."""
        return cls(
            mission=MissionPlan(grid=3, spacing_m=20.0),
            speedup=20.0,
            # At speed-up 20 a picture leaves every ~0.3 s, keeping the 25 Mbit/s link
            # busy: a preparation may not catch up before the short mission ends, and is
            # forced (the shape of the run is what CI checks).
            prepare_timeout_s=1.0,
        )

    def with_options(self, speedup: float | None, flush_limit: int | None) -> TimelineSettings:
        """These settings with the command line's speed-up and flush limit, where given."""
        return replace(
            self,
            speedup=self.speedup if speedup is None else speedup,
            flush_limit=self.flush_limit if flush_limit is None else flush_limit,
        )

    def plan(self, handovers: tuple[tuple[int, int], ...], prepared: bool = False) -> TestbedPlan:
        """The testbed plan with ``handovers``: the paper's (forced, store-and-forward),
        or baton's prepared ones on its cut-through ring."""
        return TestbedPlan(
            config=local_config(
                self.controllers,
                flush_limit=self.flush_limit,
                prepare_timeout=self.prepare_timeout_s if prepared else None,
                ring={"forwarding": "cut-through" if prepared else "store-and-forward"},
                speedup=self.speedup,
            ),
            handovers=handovers,
            prepared=prepared,
            mission=self.mission,
            resolution=self.resolution,
        )


def grid_calls(snapshot: Snapshot) -> list[Call]:
    """The run's calls, with the grid mission's request sizes."""
    calls = audit_calls(snapshot)
    return [replace(c, request_bytes=REQUEST_BYTES.get(c.method, c.request_bytes)) for c in calls]


def core_range(calls: list[Call]) -> tuple[int, int]:
    """The core of the mission: from the first picture to the last one."""
    pictures = [c.reqnr for c in calls if c.method == TAKE_PICTURE]
    if len(pictures) < 2:
        raise ValueError("the mission took fewer than two pictures")
    return pictures[0] + 1, pictures[-1] - 1


def place_handovers(
    calls: list[Call],
    settings: TimelineSettings,
    kept: Sequence[tuple[int, int]] = (),
    arrivals: Mapping[int, float] | None = None,
) -> list[tuple[int, int]]:
    """Handovers (after reqnr, new master) where the master's log is near each target.

    ``kept`` are handovers already placed well; the rest are placed one after
    the other, each on the log computed with the handovers before it (a
    handover empties the master's log). Only position polls are picked: a
    handover right after a picture lets the drone's notice race the picture's
    reply (footnote 2), and the old master would hand over a log without it.
    Given the requests' ``arrivals`` (seconds), polls are preferred where the
    last flush has had time to cross the link (else a handover at an "empty"
    log still waits for that flush, the worst case instead of the best).
    """
    methods = {c.reqnr: c.method for c in calls}

    def poll(p: LogPoint) -> bool:
        return methods[p.reqnr] == GET_POSITION

    start, end = core_range(calls)
    placed = list(kept)
    for k in range(len(kept), len(settings.targets)):
        # Spread the handovers over the core: the k-th in the k-th part of it.
        part = (end - start) // len(settings.targets)
        lowest = max(placed[-1][0] + 1 if placed else start, start + k * part)
        highest = max(lowest, start + (k + 1) * part)
        all_points = master_log_sizes(calls, settings.flush_limit, [r for r, _ in placed])
        settled = _settled(all_points, arrivals or {}, settings)
        pick = None
        # Legs differ in length (a loaded machine polls more on some), so the
        # k-th part may hold no log near the target: then the rest of the core.
        for window_end in (highest, end):
            points = [p for p in all_points if lowest <= p.reqnr <= window_end]
            pick = pick_in_stretch(
                points,
                settings.targets[k],
                settings.tolerance,
                lambda p, settled=settled: poll(p) and p.reqnr in settled,  # type: ignore[misc]
            ) or pick_in_stretch(points, settings.targets[k], settings.tolerance, poll)
            if pick is not None:
                break
        if pick is None:
            raise ValueError(
                f"no position poll in reqnr {lowest}..{end} with a log of about "
                f"{settings.targets[k] / MB:g} MB"
            )
        placed.append((pick, (k + 1) % settings.controllers))
    return placed


def _settled(
    points: Sequence[LogPoint], arrivals: Mapping[int, float], settings: TimelineSettings
) -> set[int]:
    """Reqnrs at which the last flush has crossed the controller link (with room to spare)."""
    link = settings.plan(()).config.controller_link
    settled: set[int] = set()
    last: LogPoint | None = None
    for point in points:
        if point.flushed:
            last = point
        if point.reqnr not in arrivals:
            continue
        if last is None:
            settled.add(point.reqnr)
            continue
        needed = 1.5 * t_log(last.flushed, link.latency, link.bandwidth) + 0.1
        if arrivals[point.reqnr] - arrivals.get(last.reqnr, 0.0) >= needed:
            settled.add(point.reqnr)
    return settled


def drone_connected_after(run: Snapshot, controller: int, since: float) -> float:
    """When ``controller`` next connected to the drone after ``since`` (its status's
    ``drone_connected_at``); NaN if it did not.

    The handover's own cost, without the mission program's poll sleep that
    may come before the new master's first request.
    """
    status = run.controllers.get(controller)
    later = [t for t in status.drone_connected_at if t >= since] if status is not None else []
    return min(later, default=math.nan)


def handover_logs(snapshot: Snapshot, flush_limit: int) -> list[int]:
    """The master's log size at each of the run's handovers."""
    handovers = [h.after_reqnr for h in snapshot.drone.handovers]
    sizes = {
        p.reqnr: p.size for p in master_log_sizes(grid_calls(snapshot), flush_limit, handovers)
    }
    return [sizes[r] for r in handovers]


def timeline_rows(snapshot: Snapshot, flush_limit: int) -> list[dict[str, Any]]:
    """One row per request: arrival, inter-arrival time, the master's log after it."""
    calls = grid_calls(snapshot)
    handovers = [h.after_reqnr for h in snapshot.drone.handovers]
    log = {p.reqnr: p for p in master_log_sizes(calls, flush_limit, handovers)}
    audit = sorted(snapshot.drone.audit, key=lambda a: a.reqnr)
    rows = []
    previous = None
    for a in audit:
        rows.append(
            {
                "reqnr": a.reqnr,
                "method": a.method.rsplit("/", 1)[-1],
                "controller": a.controller_id,
                "received_at": a.received_at,
                "inter_arrival_s": (a.received_at - previous) if previous is not None else 0.0,
                "reply_bytes": a.reply_bytes,
                "log_bytes": log[a.reqnr].size,
                "flushed_bytes": log[a.reqnr].flushed,
                "handover_after": a.reqnr in handovers,
            }
        )
        previous = a.received_at
    return rows


def draw_timeline(
    rows: Sequence[Mapping[str, Any]],
    handovers: Sequence[int],
    flush_limit: int,
    path: Path | BinaryIO,
    title: str | None = None,
) -> None:
    """The Figure 5 plot of one run's ``timeline_rows`` with its ``handovers`` (reqnrs),
    for the benchmark and for the testbed's HTML report."""
    from baton.bench.plots import plot_timeline

    plot_timeline(
        [r["reqnr"] for r in rows],
        [r["inter_arrival_s"] for r in rows],
        # At a flush, the log as it was sent (f + e at most), then empty.
        [r["flushed_bytes"] or r["log_bytes"] for r in rows],
        handovers,
        flush_limit,
        path,
        title,
    )


# Each run of the timeline bench waits this long at most.
RUN_TIMEOUT_S = 600.0


async def run_timeline(settings: TimelineSettings, out: Path) -> dict[str, Any]:
    """Dry run, placement, measured run; writes timeline.{png,json,csv} under ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    runs = out / "timeline-runs"
    placed = await measure_placed_handovers(settings, runs)
    measured, handovers = placed.measured, placed.handovers
    prepared = await run_plan(
        settings.plan(handovers, prepared=True),
        runs / "prepared",
        RUN_TIMEOUT_S,
        "timeline prepared",
    )
    rows = timeline_rows(measured, settings.flush_limit)
    records = handover_records(measured, rows, settings, placed.workdir)
    prepared_rows = timeline_rows(prepared, settings.flush_limit)
    prepared_records = handover_records(prepared, prepared_rows, settings, runs / "prepared")
    add_preparation_limits(prepared_records, handovers, prepared_rows, settings)
    result = {
        "settings": {
            "mission": settings.mission.__dict__,
            "flush_limit": settings.flush_limit,
            "speedup": settings.speedup,
            "resolution": settings.resolution,
            "controllers": settings.controllers,
        },
        "machine": machine(),
        "requests": len(rows),
        "dry_run_requests": placed.dry_requests,
        "attempts": placed.attempts,
        "poll_inter_arrival_median_s": poll_median(rows),
        "after_picture_inter_arrival_median_s": after_picture_median(rows),
        "handovers": records,
        "prepared_handovers": prepared_records,
    }
    write_timeline(
        out,
        result,
        rows,
        {"timeline.png": (measured, rows), "timeline-prepared.png": (prepared, prepared_rows)},
        settings.flush_limit,
    )
    return result


@dataclass(frozen=True)
class PlacedRun:
    """The measured run of the paper's handovers, placed where the log is near its targets."""

    measured: Snapshot
    handovers: tuple[tuple[int, int], ...]  # (after reqnr, new master), as the run made them
    workdir: Path  # the measured run's folder (its logs)
    dry_requests: int  # the requests of the dry run without handovers
    attempts: list[dict[str, Any]]  # each attempt's handovers and logs at them


async def measure_placed_handovers(settings: TimelineSettings, runs: Path) -> PlacedRun:
    """A dry run for the request sequence, then measured runs with the handovers placed
    from the last run, until every log at a handover is near its target (at most
    ``settings.attempts`` measured runs)."""
    reference = await run_plan(settings.plan(()), runs / "dry", RUN_TIMEOUT_S, "timeline dry run")
    dry_requests = len(reference.drone.audit)
    kept: list[tuple[int, int]] = []
    attempts = []
    for attempt in range(1, settings.attempts + 1):
        arrivals = {a.reqnr: a.received_at for a in reference.drone.audit}
        handovers = tuple(place_handovers(grid_calls(reference), settings, kept, arrivals))
        say(f"timeline: attempt {attempt}: handovers (after reqnr, new master) {handovers}")
        workdir = runs / f"measured-{attempt}"
        measured = await run_plan(settings.plan(handovers), workdir, RUN_TIMEOUT_S, "timeline")
        logs = handover_logs(measured, settings.flush_limit)
        attempts.append({"handovers": handovers, "log_bytes": logs})
        say(
            f"timeline: attempt {attempt}: logs at handovers (MB) "
            f"{[round(b / MB, 2) for b in logs]}"
        )
        off = off_target(logs, settings)
        if not off:
            break
        # Handovers shift the rest of the mission (the vehicle flies on while
        # the mission waits), so later ones are placed again on this run.
        kept = list(handovers[: off[0]])
        reference = measured
    return PlacedRun(measured, handovers, workdir, dry_requests, attempts)


def off_target(logs: Sequence[int], settings: TimelineSettings) -> list[int]:
    """The handovers (by index) whose log was farther than the tolerance from its target."""
    return [
        k
        for k, (size, target) in enumerate(zip(logs, settings.targets, strict=True))
        if abs(size - target) > settings.tolerance
    ]


def write_timeline(
    out: Path,
    result: dict[str, Any],
    rows: list[dict[str, Any]],
    figures: Mapping[str, tuple[Snapshot, list[dict[str, Any]]]],
    flush_limit: int,
) -> None:
    """timeline.json (``result``), timeline.csv (the measured run's ``rows``) and a
    figure of each run (by file name: the run and its rows) under ``out``."""
    write_json(out / "timeline.json", result)
    with (out / "timeline.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    for name, (run, run_rows) in figures.items():
        draw_timeline(
            run_rows, [h.after_reqnr for h in run.drone.handovers], flush_limit, out / name
        )


def add_preparation_limits(
    prepared: list[dict[str, Any]],
    placed: Sequence[tuple[int, int]],
    rows: list[dict[str, Any]],
    settings: TimelineSettings,
) -> None:
    """Each prepared handover's physical limit (``model.preparation_limit``): the
    master's log when the preparation began (by the model, on this run's requests and
    handovers), then every picture taken while it lasted, from when its bytes reached
    the master, over one controller link, the acknowledgement back, and the drone link
    both ways; and the ratio of the preparation to it."""
    config = settings.plan(()).config
    ring, drone = config.controller_link, config.drone_link
    replies = {r["reqnr"]: r for r in rows}
    for record, (began_after, _) in zip(prepared, placed, strict=False):
        pictures = [
            replies[n]
            for n in range(began_after + 1, record["after_reqnr"] + 1)
            if n in replies and replies[n]["method"] == "TakePicture"
        ]
        start = replies[began_after]["log_bytes"] if began_after in replies else 0
        began_at = record["prepare_started_at"]
        later = [(p["received_at"] - began_at, p["reply_bytes"]) for p in pictures]
        limit = preparation_limit(
            start, later, ring.latency, ring.bandwidth, drone.latency, drone.bandwidth
        )
        record["prepare_needed_bytes"] = start + sum(p["reply_bytes"] for p in pictures)
        record["prepare_limit_s"] = limit
        record["prepare_ratio"] = record["prepare_s"] / limit if limit else math.nan


def poll_median(rows: list[dict[str, Any]]) -> float:
    """The median inter-arrival time of the position polls."""
    polls = [r["inter_arrival_s"] for r in rows[1:] if r["method"] == "GetPosition"]
    return statistics.median(polls) if polls else 0.0


def after_picture_median(rows: list[dict[str, Any]]) -> float:
    """The median inter-arrival time of the request after a picture."""
    by_reqnr = {r["reqnr"]: r for r in rows}
    pictures = [
        by_reqnr[r["reqnr"] + 1]["inter_arrival_s"]
        for r in rows
        if r["method"] == "TakePicture" and r["reqnr"] + 1 in by_reqnr
    ]
    return statistics.median(pictures) if pictures else 0.0


def handover_records(
    run: Snapshot, rows: list[dict[str, Any]], settings: TimelineSettings, workdir: Path
) -> list[dict[str, Any]]:
    """Each handover of ``run``: its delay, what it cost the mission, its kind. A prepared
    one placed near the mission's end may not be carried out before the mission ends (its
    preparation outlasts the mission): the run then has fewer than three."""
    by_reqnr = {r["reqnr"]: r for r in rows}
    records: list[dict[str, Any]] = []
    done = [h for h in run.drone.handovers if h.trigger == drone_pb2.HANDOVER_TRIGGER_SCRIPT]
    for target, h in zip(settings.targets, done, strict=False):
        # The next request the drone saw (Clock calls never reach it).
        first = min((r for r in by_reqnr if r > h.after_reqnr), default=0)
        records.append(
            {
                "after_reqnr": h.after_reqnr,
                "new_master": h.new_master,
                "target_bytes": target,
                # Prepared: what the new master lacked when the drone moved the master.
                "log_bytes": (
                    h.prepare_lacked_bytes
                    if h.kind == drone_pb2.HANDOVER_KIND_PREPARED
                    else by_reqnr[h.after_reqnr]["log_bytes"]
                ),
                "delay_s": h.delay_s,
                "ready_s": drone_connected_after(run, h.new_master, h.decided_at) - h.decided_at,
                "inter_arrival_s": by_reqnr[first]["inter_arrival_s"] if first in by_reqnr else 0,
                "kind": label(drone_pb2.HandoverKind, h.kind),
                "prepare_s": h.decided_at - h.prepare_started_at if h.prepare_started_at else 0.0,
                "prepare_started_at": h.prepare_started_at,
                "prepare_timed_out": h.prepare_timed_out,
            }
        )
    median = poll_median(rows)
    for record in records:
        # What the handover added over the request's usual spacing: the new
        # master's program sleeps one poll period too, as the old one would.
        record["extra_s"] = record["inter_arrival_s"] - median
    return records


def table(result: dict[str, Any]) -> str:
    """The handovers of the measured runs as a markdown table: the paper's, then the
    same ones prepared."""
    rows = [
        [
            h["kind"],
            f"{h['prepare_s'] * 1e3:.0f}" if h["prepare_s"] else "-",
            h["after_reqnr"],
            h["new_master"],
            f"{h['target_bytes'] / MB:g}",
            f"{h['log_bytes'] / MB:.2f}",
            f"{h['delay_s'] * 1e3:.0f}",
            f"{h['ready_s'] * 1e3:.0f}",
            f"{h['inter_arrival_s'] * 1e3:.0f}",
            f"{h['extra_s'] * 1e3:.0f}",
            f"{h['prepare_needed_bytes'] / MB:.2f}" if "prepare_limit_s" in h else "-",
            f"{h['prepare_limit_s'] * 1e3:.0f}" if "prepare_limit_s" in h else "-",
            f"{h['prepare_ratio']:.2f}" if "prepare_limit_s" in h else "-",
        ]
        for h in [*result["handovers"], *result.get("prepared_handovers", [])]
    ]
    text = markdown_table(
        [
            "kind",
            "preparation (ms)",
            "after reqnr",
            "new master",
            "target log (MB)",
            "log at handover (MB)",
            "handover delay (ms)",
            "new master ACTIVE and connected (ms)",
            "inter-arrival (ms)",
            "extra over a poll (ms)",
            "preparation had to send (MB)",
            "its physical limit (ms)",
            "preparation / limit",
        ],
        rows,
    )
    return (
        text + f"\nrequests: {result['requests']}; median inter-arrival of polls "
        f"{result['poll_inter_arrival_median_s'] * 1e3:.0f} ms, after a picture "
        f"{result['after_picture_inter_arrival_median_s'] * 1e3:.0f} ms "
        f"(speed-up {result['settings']['speedup']:g})\n"
    )
