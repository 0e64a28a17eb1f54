"""``baton testbed``: run the paper's mission on the local testbed, show progress, report.

Also ``baton testbed report``: follow a testbed that runs elsewhere (the
compose testbed) through its status RPCs and write the same report.
"""

from __future__ import annotations

import asyncio
import json
import shlex
import sys
import time
from pathlib import Path
from typing import Any

from baton.bench.timeline import timeline_rows
from baton.config import BatonConfig
from baton.lifecycle import write_atomically
from baton.missions.plan import load_plan
from baton.rpc.channels import aio_channel
from baton.rpc.labels import label
from baton.rpc.tls import OPERATOR, Identity
from baton.testbed.faults import fault_lines, fault_outcomes
from baton.testbed.flight_map import Track, flight_geojson
from baton.testbed.html_report import write_page
from baton.testbed.local import LocalTestbed, MissionPlan, Snapshot, TestbedPlan, drone_status
from baton.testbed.report import build_report, run_succeeded, summary_table
from baton.testbed.supervisor import PartDied, PartNotReady
from baton.testbed.waits import WaitLog, part_waits, waits_line
from baton.v1 import drone_pb2, drone_pb2_grpc, ring_pb2, ring_pb2_grpc


class Progress:
    """One status line a second: waypoint k of n, the master, each controller's state."""

    def __init__(
        self,
        waypoints: int,
        planned_handovers: int,
        stream: Any = sys.stdout,
        what: str = "waypoint",
    ) -> None:
        self.waypoints = waypoints  # pictures expected, one a waypoint for "waypoint"
        self.what = what
        self.planned = planned_handovers
        self.stream = stream
        self.started = time.monotonic()
        self._last = 0.0
        # Every part's waits over the run, for the report.
        self.waits = WaitLog()

    def _due(self) -> bool:
        now = time.monotonic()
        if now - self._last < 1.0:
            return False
        self._last = now
        return True

    def event(self, text: str) -> None:
        """Something that happened to a part (a fault, a death, a restart), at once."""
        print(f"{self._stamp()} {text}", file=self.stream, flush=True)

    def _stamp(self) -> str:
        return f"[{time.monotonic() - self.started:6.1f}s]"

    def vehicle_wait(self, drone: drone_pb2.DroneStatus) -> None:
        """Before the mission: why the vehicle is not ready to arm yet."""
        if not self._due():
            return
        state = drone.flight_state
        why = drone.vehicle.problem or state.not_ready_reason or "connecting"
        autopilot = f" ({state.autopilot} {state.autopilot_mode})" if state.autopilot else ""
        print(
            f"{self._stamp()} waiting for the vehicle{autopilot}: {why}",
            file=self.stream,
            flush=True,
        )

    def __call__(self, snapshot: Snapshot) -> None:
        waits = part_waits(snapshot.drone, snapshot.controllers)
        self.waits.add(waits, time.monotonic() - self.started)
        if not self._due():
            return
        states = " ".join(
            f"c{cid}:{label(ring_pb2.ControllerState, c.state)[0]}"
            f"{'*' if c.master else ''}@{c.reqnr}"
            for cid, c in sorted(snapshot.controllers.items())
        )
        drone = snapshot.drone
        scripted = sum(1 for h in drone.handovers if h.trigger == drone_pb2.HANDOVER_TRIGGER_SCRIPT)
        takeovers = sum(1 for h in drone.handovers if h.kind == drone_pb2.HANDOVER_KIND_TAKEOVER)
        operator = sum(
            1
            for h in drone.handovers
            if h.trigger == drone_pb2.HANDOVER_TRIGGER_RPC
            and h.kind != drone_pb2.HANDOVER_KIND_TAKEOVER
        )
        policy = sum(1 for h in drone.handovers if h.trigger == drone_pb2.HANDOVER_TRIGGER_POLICY)
        others = f" + {policy} by policy" if policy else ""
        others += (f" + {operator} by operator" if operator else "") + (
            f" | takeovers {takeovers}" if takeovers else ""
        )
        vehicle = "".join(
            f" | {how}: {', '.join(sorted(n for n, h in snapshot.absent.items() if h == how))}"
            for how in ("dead", "stopped", "cut")
            if how in snapshot.absent.values()
        )
        vehicle += "" if drone.vehicle.healthy else f" | vehicle: {drone.vehicle.problem}"
        if drone.HasField("failsafe"):  # the safety net took the vehicle (docs/operating.md)
            vehicle += f" | FAILSAFE {drone.failsafe.action}: {drone.failsafe.reason}"
        if drone.HasField("paused"):  # an operator's pause (docs/operating.md)
            vehicle += f" | PAUSED: {drone.paused.reason}"
        if drone.HasField("ended"):
            vehicle += f" | ENDED: {drone.ended.reason}"
        vehicle += "".join(
            f" | c{cid} log file NOT DURABLE (whole up to {c.log_file.whole_up_to_lognr})"
            for cid, c in sorted(snapshot.controllers.items())
            if c.log_file.path and not c.log_file.durable
        )
        vehicle += waits_line(waits)
        print(
            f"{self._stamp()} "
            + (
                f"waypoint {snapshot.pictures}/{self.waypoints}"
                if self.waypoints and self.what == "waypoint"
                else f"pictures {snapshot.pictures}"
                + (f"/{self.waypoints}" if self.waypoints else "")
            )
            + " | "
            + f"master {drone.master} | reqnr {drone.last_reqnr} | "
            f"handovers {scripted}/{self.planned}{others} | {states}{vehicle}",
            file=self.stream,
            flush=True,
        )


def files_note(files: dict[str, Any]) -> str:
    """Where the run's logs are, and the command that replays them."""
    mission = files["mission"]
    args = "".join(f" --mission-arg {shlex.quote(arg)}" for arg in mission["args"])
    tlogs = ", ".join(files["tlogs"]) or "none"
    return (
        f"controller logs: {', '.join(files['controller_logs'].values())}\n"
        f"replay them: baton replay {files['workdir']} --mission {mission['file']}{args}\n"
        f"telemetry log (.tlog): {tlogs}"
    )


def write_report(report: dict[str, Any], path: Path) -> None:
    """Writes the report JSON (creating the folder)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2) + "\n")


def add_faults(report: dict[str, Any], testbed: LocalTestbed) -> None:
    """The run's faults and the parts that died, with the mission's verdict, into the
    report (``faults``, ``parts_died``, ``ended_early``)."""
    verdict = (
        f"{'COMPLETED' if report['completed'] else 'NOT COMPLETED'}, exactly once: "
        f"{bool(report['exactly_once'] and report['side_effects']['exactly_once'] is not False)}"
        f", replicas consistent: {report['replicas_consistent']}"
    )
    report["faults"] = fault_outcomes(testbed.injector.records, report, verdict)
    report["parts_died"] = [death.to_json() for death in testbed.deaths]
    report["ended_early"] = testbed.ended_early or None


async def run_local(plan: TestbedPlan, workdir: Path, report_path: Path, timeout: float) -> int:
    """Runs one mission on the local testbed; returns the exit code."""
    planned = plan.config
    print(
        f"baton testbed: {plan.describe_mission()}, {len(planned.controllers)} controllers, "
        f"handover policy {planned.handover_policy.name}, flush limit {planned.flush_limit} "
        "bytes, handovers "
        f"{', '.join(f'{r}:{m}' for r, m in plan.handovers) or 'none'}, "
        f"speed-up {planned.speedup}x, "
        f"vehicle {plan.vehicle}; "
        f"logs in {workdir / 'logs'}",
        flush=True,
    )
    started = time.monotonic()
    testbed = LocalTestbed(plan, workdir)
    # The plan as the mission flies it: with the run's end=... if it was given one.
    end = [a.partition("=")[2] for a in plan.all_mission_args() if a.startswith("end=")]
    flight_plan = (
        load_plan(str(plan.flight_plan), end[-1] if end else "")
        if plan.flight_plan is not None
        else None
    )
    try:
        # A survey (grid or corridor) takes a picture at each waypoint; a plan, where it says.
        survey = plan.mission_file is None
        targets = plan.mission.targets()
        pictures = len(targets) if survey else 0
        if flight_plan is not None:
            pictures = flight_plan.pictures or 0
        progress = Progress(
            pictures, len(plan.handovers), what="waypoint" if survey else "pictures"
        )
        track = Track()
        testbed.say = progress.event

        def follow(snapshot: Snapshot) -> None:
            progress(snapshot)
            track(snapshot, time.time())

        config = await testbed.start(progress.vehicle_wait)
        write_atomically(
            workdir / "pids.json",
            json.dumps(
                {name: p.process.pid for name, p in testbed.supervisor.parts.items() if p.process}
            ),
        )
        snapshot = await testbed.run_mission(timeout, follow)
    except (PartDied, PartNotReady) as exc:
        print(f"baton testbed: FAILED: {exc}", file=sys.stderr, flush=True)
        return 1
    except TimeoutError as exc:
        print(f"baton testbed: FAILED: {exc}", file=sys.stderr, flush=True)
        return 1
    finally:
        await testbed.stop()
    report = build_report(
        config,
        snapshot,
        plan.mission.grid,
        time.monotonic() - started,
        list(plan.handovers),
        plan.mission.spacing_m,
        flight_plan,
        grid_mission=survey,
        targets=targets if plan.mission.kind != "grid" else None,
    )
    report["files"] = files = testbed.files()
    report["waits"] = progress.waits.to_json()
    add_faults(report, testbed)
    write_report(report, report_path)
    print(summary_table(report), flush=True)
    for line in fault_lines(report):
        print(line, flush=True)
    print(f"report: {report_path}", flush=True)
    print(files_note(files), flush=True)
    taken = snapshot.camera_effects or []
    geojson = flight_geojson(config, report, track.points, taken)
    map_path = report_path.with_suffix(".geojson")
    map_path.write_text(json.dumps(geojson) + "\n")
    map_png = report_path.with_suffix(".png")
    page = report_path.with_suffix(".html")
    masters = " → ".join(str(m) for m in report["masters"])
    policy = report["policy"]["name"]
    drawing = time.monotonic()
    write_page(
        page,
        report,
        geojson,
        f"{plan.describe_mission()}, policy {policy}: masters {masters}",
        timeline_rows(snapshot, config.flush_limit),
        config.flush_limit,
        taken,
        testbed.thumbnails_dir,
        map_path=map_png,
        beside={"JSON report": str(report_path), "GeoJSON map": str(map_path)},
    )
    print(f"map: {map_path} (GeoJSON), {map_png}", flush=True)
    print(
        f"HTML report: {page} ({page.stat().st_size:,} bytes, drawn in "
        f"{time.monotonic() - drawing:.1f} s)",
        flush=True,
    )
    return 0 if run_succeeded(report) and not report["handovers_missed"] else 1


async def follow_remote(
    config: BatonConfig,
    mission: MissionPlan,
    report_path: Path,
    timeout: float,
    handovers: list[tuple[int, int]],
) -> int:
    """Waits for a testbed running elsewhere to fly ``mission`` (the grid or the
    corridor its controllers were given), then reports."""
    started = time.monotonic()
    tls = config.tls_for(OPERATOR)
    drone_channel = aio_channel(config.drone.address, tls, config.drone_identity)
    channels = {
        c.id: aio_channel(c.reach, tls, Identity.controller(c.id)) for c in config.controllers
    }
    drone = drone_pb2_grpc.DroneStub(drone_channel)
    rings = {cid: ring_pb2_grpc.ControllerRingStub(ch) for cid, ch in channels.items()}
    targets = mission.targets()
    progress = Progress(len(targets), len(handovers))
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    try:
        while True:
            try:
                snapshot = Snapshot(await drone_status(drone, wait_for_ready=True))
                for cid, stub in rings.items():
                    snapshot.controllers[cid] = await stub.GetStatus(
                        ring_pb2.GetControllerStatusRequest(), timeout=10, wait_for_ready=True
                    )
            except Exception as exc:  # a service still starting: keep waiting
                if loop.time() > deadline:
                    print(f"baton testbed report: FAILED: {exc}", file=sys.stderr)
                    return 1
                await asyncio.sleep(1.0)
                continue
            progress(snapshot)
            if snapshot.missions_ended:
                break
            if loop.time() > deadline:
                print("baton testbed report: FAILED: mission not finished in time", file=sys.stderr)
                return 1
            await asyncio.sleep(0.5)
    finally:
        await drone_channel.close()
        for channel in channels.values():
            await channel.close()
    report = build_report(
        config,
        snapshot,
        mission.grid,
        time.monotonic() - started,
        handovers,
        targets=targets if mission.kind != "grid" else None,
    )
    report["waits"] = progress.waits.to_json()
    write_report(report, report_path)
    print(summary_table(report), flush=True)
    return 0 if run_succeeded(report) else 1
