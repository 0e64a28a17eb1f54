"""The testbed report: what happened in a mission, checked against the drone's audit
and, independently of it, against the side effects counted where they happened.

``build_report`` turns the final status of the drone and of every controller
into one JSON document (format ``baton.testbed.report/1``, described in
docs/operating.md, "The report"), and ``summary_table`` prints it for a
person. The same report comes out of the local testbed and of the compose
testbed. ``check_side_effects`` is the skeptic's exactly-once check: it
trusts neither the drone's audit nor the controllers, only what the sim
vehicle and the camera counted (``baton.effects``), held against what the
grid mission asks for.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from typing import Any

from baton.bench.model import t_max
from baton.config import BatonConfig
from baton.missions.grid import waypoints
from baton.missions.plan import Plan
from baton.rpc.labels import label
from baton.rpc.methods import path
from baton.sdk import Position, distance_m, offset
from baton.testbed.local import TAKE_PICTURE, Effects, Snapshot
from baton.testbed.waits import report_lines
from baton.v1 import drone_pb2, ring_pb2

REPORT_FORMAT = "baton.testbed.report/1"
# What the report says for a part that keeps no effects file (SITL, an
# autopilot that runs already, the compose testbed).
NOT_COUNTED = "not counted"
# The grid mission's commands the vehicle must act on exactly once each.
ONCE_PER_MISSION = ("arm", "takeoff", "land")
# How far a goto's target may be from its grid waypoint: the target crosses
# MAVLink as 1e-7 degrees (about 1 cm).
GOTO_TOLERANCE_M = 0.5
GOTO = path("Mobility.Goto")


def check_side_effects(
    snapshot: Snapshot,
    grid: int,
    spacing_m: float | None = None,
    targets: Sequence[tuple[float, float]] | None = None,
) -> dict[str, Any]:
    """The grid mission's side effects, as the camera and the vehicle counted them
    (or another survey's: ``targets``, its waypoints north and east of the first).

    Exactly once means: the camera produced one picture per waypoint
    (``grid``² pictures, each of which the mission checked as taken at its
    waypoint); the vehicle acted on one arm, one takeoff and one land, and on
    one goto per waypoint, in the grid's order (a serpentine from the first
    target, ``spacing_m`` apart; when not given, inferred from the first
    target and the next one elsewhere). Speed and mode changes are counted
    and shown, not checked: the drone service sends them as the autopilot
    needs. ``exactly_once`` is None when neither part counted anything; a
    part that did not count is ``NOT_COUNTED`` and not held against the run.
    """
    problems: list[str] = []
    expected = grid * grid if targets is None else len(targets)
    plan = f"the {grid}x{grid} grid" if targets is None else "the survey"
    pictures = _count_pictures(snapshot, expected, f"{plan} takes", problems)
    vehicle = snapshot.vehicle_effects
    commands: dict[str, int] | str = NOT_COUNTED
    if vehicle is not None:
        counts = Counter(e["effect"] for e in vehicle)
        commands = dict(sorted(counts.items()))
        for name in ONCE_PER_MISSION:
            if counts[name] != 1:
                problems.append(f"the vehicle acted on {counts[name]} {name} commands, not 1")
        gotos = [e for e in vehicle if e["effect"] == "goto"]
        gotos = _without_resumes(gotos, snapshot)
        if targets is None:
            spacing = spacing_m if spacing_m is not None else _grid_spacing(gotos)
            targets = waypoints(grid, spacing)
        problems += _goto_problems(gotos, targets, plan)
    return _effects(pictures, expected, commands, problems)


def resent_gotos(snapshot: Snapshot) -> int:
    """The gotos the drone sent again on its own: each resume of the drone's handover
    policy (a leg flown on after a hold, ``DroneStatus.policy_resumes``, kept across the
    drone's restarts) and each operator's resume that flew a leg on after a pause, shown
    in the report's ``policy`` and ``operator_commands``."""
    drone = snapshot.drone
    return drone.policy_resumes + sum(
        c.command == "resume" and c.action == "goto" and c.vehicle == "accepted"
        for c in drone.operator_commands
    )


def _without_resumes(gotos: Effects, snapshot: Snapshot) -> Effects:
    """The gotos the mission asked for: each the drone sent again on its own
    (``resent_gotos``: the last one again) is not counted against the mission."""
    resumes = resent_gotos(snapshot)
    kept: Effects = []
    for goto in gotos:
        if resumes and kept and _same_target(kept[-1], goto):
            resumes -= 1
            continue
        kept.append(goto)
    return kept


def _same_target(a: dict[str, Any], b: dict[str, Any]) -> bool:
    first = Position(a["latitude_deg"], a["longitude_deg"], 0.0, 0.0)
    return distance_m(first, Position(b["latitude_deg"], b["longitude_deg"], 0.0, 0.0)) < 0.01


def _grid_spacing(gotos: Effects) -> float:
    """The grid's spacing, from its gotos: its second waypoint is one spacing east of its first."""
    targets = [Position(g["latitude_deg"], g["longitude_deg"], 0.0, 0.0) for g in gotos]
    return next(
        (d for t in targets[1:] if (d := distance_m(targets[0], t)) > GOTO_TOLERANCE_M), 0.0
    )


def _goto_problems(
    gotos: Effects, waypoints_ne: Sequence[tuple[float, float]], plan: str
) -> list[str]:
    """What is wrong with the gotos the vehicle acted on, for a survey of ``waypoints_ne``
    (metres north and east of its first)."""
    targets = [Position(g["latitude_deg"], g["longitude_deg"], 0.0, 0.0) for g in gotos]
    problems = []
    repeated = Counter((round(t.latitude_deg, 6), round(t.longitude_deg, 6)) for t in targets)
    for (lat, lon), times in repeated.items():
        if times > 1:
            problems.append(f"the vehicle acted on a goto to {lat}, {lon} {times} times")
    if len(targets) != len(waypoints_ne):
        problems.append(
            f"the vehicle acted on {len(targets)} gotos; {plan} has {len(waypoints_ne)} waypoints"
        )
    if not targets:
        return problems
    first_north, first_east = waypoints_ne[0]
    for k, (target, (north, east)) in enumerate(zip(targets, waypoints_ne, strict=False), start=1):
        expected = offset(targets[0], north - first_north, east - first_east)
        off = distance_m(target, expected)
        if off > GOTO_TOLERANCE_M:
            where = "of the grid" if plan.endswith("grid") else f"of {plan}"
            problems.append(f"goto {k} flew to {off:.1f} m from waypoint {k} {where}")
            break  # the first one out of order says it; the rest follow from it
    return problems


def check_plan_effects(snapshot: Snapshot, plan: Plan, pictures_asked: int) -> dict[str, Any]:
    """A QGroundControl plan's side effects, as the camera and the vehicle counted them.

    Exactly once means: the camera produced the plan's pictures (for a plan that
    triggers by distance, as many as the mission asked the drone for,
    ``pictures_asked``); the vehicle acted on one arm, one takeoff, one land or
    return to launch as the plan ends, and on one goto per waypoint of the plan,
    in its order, at its position and, against the first, its altitude.
    """
    problems: list[str] = []
    expected = plan.pictures if plan.pictures is not None else pictures_asked
    pictures = _count_pictures(snapshot, expected, "the plan takes", problems)
    vehicle = snapshot.vehicle_effects
    commands: dict[str, int] | str = NOT_COUNTED
    if vehicle is not None:
        counts = Counter(e["effect"] for e in vehicle)
        commands = dict(sorted(counts.items()))
        # MAVSDK returns to launch and holds by the autopilot's modes, not by commands.
        for name, mode in (("return_to_launch", "RETURN_TO_LAUNCH"), ("hold", "HOLD")):
            counts[name] += sum(
                1 for e in vehicle if e["effect"] == "set_mode" and e["mode"] == mode
            )
        for name in ("arm", "takeoff", plan.end):
            if counts[name] != 1:
                problems.append(f"the vehicle acted on {counts[name]} {name} commands, not 1")
        problems += _steps_problems(vehicle, plan)
        gotos = [e for e in vehicle if e["effect"] == "goto"]
        wanted = plan.waypoints
        if len(gotos) != len(wanted):
            problems.append(
                f"the vehicle acted on {len(gotos)} gotos; the plan has {len(wanted)} waypoints"
            )
        for k, (goto, item) in enumerate(zip(gotos, wanted, strict=False), start=1):
            off = distance_m(
                Position(goto["latitude_deg"], goto["longitude_deg"]),
                Position(item.latitude_deg, item.longitude_deg),
            )
            climb = goto["altitude_amsl_m"] - gotos[0]["altitude_amsl_m"]
            planned = item.altitude_m - wanted[0].altitude_m
            if off > GOTO_TOLERANCE_M or abs(climb - planned) > GOTO_TOLERANCE_M:
                problems.append(
                    f"goto {k} flew to {off:.1f} m from {item.where} of the plan, "
                    f"{climb - planned:+.1f} m off its altitude"
                )
                break  # the first one out of order says it; the rest follow from it
    return _effects(pictures, expected, commands, problems)


def _steps_problems(vehicle: Effects, plan: Plan) -> list[str]:
    """What is off in the order of the gotos and regions of interest the vehicle acted
    on, against the plan's (its loops expanded: each waypoint once a lap, the ROI set
    and cleared between the waypoints the plan puts it)."""
    names = {name for name, _ in plan.vehicle_steps}
    acted = [e["effect"] for e in vehicle if e["effect"] in names | {"roi", "roi_none"}]
    wanted = [name for name, _ in plan.vehicle_steps]
    if acted == wanted:
        return []
    k = next(
        (k for k, (a, w) in enumerate(zip(acted, wanted, strict=False)) if a != w),
        min(len(acted), len(wanted)),
    )
    where = plan.vehicle_steps[k][1].where if k < len(wanted) else "after the plan's last step"
    return [
        f"the vehicle's {k + 1}th step was {acted[k] if k < len(acted) else 'missing'}; the "
        f"plan's is {wanted[k] if k < len(wanted) else 'none'} ({where}); it acted on "
        f"{len(acted)} steps of the plan's {len(wanted)}"
    ]


def _effects(
    pictures: int | str, expected: int, commands: dict[str, int] | str, problems: list[str]
) -> dict[str, Any]:
    """A side-effect check's verdict: what was counted, what is off, and exactly once
    (None when neither the camera nor the vehicle counted anything)."""
    counted = pictures != NOT_COUNTED or commands != NOT_COUNTED
    return {
        "pictures_taken": pictures,
        "pictures_expected": expected,
        "vehicle_commands": commands,
        "problems": problems,
        "exactly_once": not problems if counted else None,
    }


def _count_pictures(snapshot: Snapshot, expected: int, what: str, problems: list[str]) -> int | str:
    """The pictures the camera produced (``NOT_COUNTED`` if it kept no file); a count
    other than ``expected`` is a problem, said as "... {what} {expected}"."""
    camera = snapshot.camera_effects
    if camera is None:
        return NOT_COUNTED
    pictures = sum(1 for e in camera if e["effect"] == "picture")
    if pictures != expected:
        problems.append(f"the camera produced {pictures} pictures; {what} {expected}")
    return pictures


def check_counted_effects(snapshot: Snapshot, pictures_asked: int) -> dict[str, Any]:
    """Side effects of a mission file the report knows nothing of: the camera must have
    produced one picture for each TakePicture the drone executed; the vehicle's commands
    are counted and shown, not checked."""
    vehicle = snapshot.vehicle_effects
    problems: list[str] = []
    pictures = _count_pictures(snapshot, pictures_asked, "the mission asked for", problems)
    commands: dict[str, int] | str = NOT_COUNTED
    if vehicle is not None:
        commands = dict(sorted(Counter(e["effect"] for e in vehicle).items()))
    return _effects(pictures, pictures_asked, commands, problems)


def build_report(
    config: BatonConfig,
    snapshot: Snapshot,
    grid: int,
    duration_s: float,
    planned_handovers: list[tuple[int, int]],
    spacing_m: float | None = None,
    plan: Plan | None = None,
    grid_mission: bool = True,
    targets: Sequence[tuple[float, float]] | None = None,
) -> dict[str, Any]:
    """The report of one mission run (``spacing_m``: the grid's, if known; ``plan``: the
    QGroundControl plan flown instead of the grid, if one was; ``grid_mission`` False
    for another mission file, whose side effects are only counted; ``targets``: another
    survey's waypoints, north and east of its first, instead of the grid)."""
    drone = snapshot.drone
    audit = list(drone.audit)
    pictures = sum(1 for a in audit if a.method == TAKE_PICTURE)
    largest_entry = max((a.reply_bytes for a in audit), default=0)
    t_conns = [t for c in snapshot.controllers.values() for t in c.t_conn_s]
    t_conn = sum(t_conns) / len(t_conns) if t_conns else 0.0
    handovers = [
        _handover(config, snapshot, record, largest_entry, t_conn) for record in drone.handovers
    ]
    # A scripted reqnr that was a Clock call fires after the next drone request. Only
    # the script's handovers stand for planned ones (not an operator's, not a takeover).
    scripted = [h for h in handovers if h["trigger"] == "script"]
    missed = planned_handovers[len(scripted) :]
    return {
        "format": REPORT_FORMAT,
        "completed": bool(snapshot.controllers)
        and all(c.mission == ring_pb2.MISSION_STATE_DONE for c in snapshot.controllers.values()),
        "duration_s": round(duration_s, 3),
        "mission": _mission(snapshot, grid, plan, grid_mission, targets),
        "setup": _setup(config, drone, t_conn, largest_entry),
        "handovers": handovers,
        # The master at the start, then after each handover.
        "masters": [config.master_id, *(h["to"] for h in handovers)],
        "policy": _policy(config, drone),
        "handovers_planned": [list(h) for h in planned_handovers],
        "handovers_missed": [list(h) for h in missed],
        "drone": {
            "master": drone.master,
            "last_reqnr": drone.last_reqnr,
            "executed": drone.executed,
            "duplicates": drone.duplicates,
            "rejected": drone.rejected,
            "vehicle_outages": drone.vehicle.outages,
            # The failsafe the vehicle is in at the end (docs/operating.md, "The safety
            # net"); None: the mission had the vehicle.
            "failsafe": (
                {
                    "cause": drone.failsafe.cause,
                    "action": drone.failsafe.action,
                    "since": drone.failsafe.since,
                    "reason": drone.failsafe.reason,
                }
                if drone.HasField("failsafe")
                else None
            ),
            # Every operator command (docs/operating.md, "Operator commands"): when,
            # after which request, what the vehicle was told and what it did.
            "operator_commands": [
                {
                    "command": c.command,
                    "at": c.at,
                    "after_reqnr": c.after_reqnr,
                    "action": c.action,
                    "vehicle": c.vehicle,
                    "by": c.by,
                    "reason": c.reason,
                }
                for c in drone.operator_commands
            ],
        },
        "controllers": [_controller(cid, c) for cid, c in sorted(snapshot.controllers.items())],
        "replicas_consistent": replicas_consistent(snapshot),
        "exactly_once": executed_exactly_once(snapshot),
        "side_effects": (
            check_plan_effects(snapshot, plan, pictures)
            if plan is not None
            else check_side_effects(snapshot, grid, spacing_m, targets)
            if grid_mission
            else check_counted_effects(snapshot, pictures)
        ),
    }


def executed_exactly_once(snapshot: Snapshot) -> bool:
    """Each request number once in the drone's audit, and as many drone calls as every
    replica's program had answered (Clock calls are logged too but never reach the
    drone, so the audit's request numbers have gaps where they were)."""
    audit = snapshot.drone.audit
    counts = Counter(a.reqnr for a in audit)
    return all(n == 1 for n in counts.values()) and all(
        c.drone_calls == len(audit) for c in snapshot.controllers.values()
    )


def replicas_consistent(snapshot: Snapshot) -> bool:
    """Every controller got the same replies (one reply chain) up to one request number,
    no earlier than the drone's last."""
    chains = {c.reply_chain for c in snapshot.controllers.values()}
    reqnrs = {c.reqnr for c in snapshot.controllers.values()}
    return len(chains) == 1 and len(reqnrs) == 1 and max(reqnrs) >= snapshot.drone.last_reqnr


def _handover(
    config: BatonConfig,
    snapshot: Snapshot,
    record: drone_pb2.HandoverRecord,
    largest_entry: int,
    t_conn: float,
) -> dict[str, Any]:
    """One handover the drone recorded, with the log it moved and the model's bound."""
    old = snapshot.controllers.get(record.old_master)
    moved = 0
    if old is not None:
        moved = next(
            (
                h.log_bytes
                for h in old.handovers
                if h.role == ring_pb2.HANDOVER_ROLE_OLD
                and h.peer == record.new_master
                and h.reqnr <= record.after_reqnr
            ),
            0,
        )
    hops = config.hops(record.old_master, record.new_master)
    link = config.controller_link
    return {
        "from": record.old_master,
        "to": record.new_master,
        "after_reqnr": record.after_reqnr,
        "hops": hops,
        "trigger": label(drone_pb2.HandoverTrigger, record.trigger),
        "kind": label(drone_pb2.HandoverKind, record.kind),
        # A takeover: from the drone's last sighting of the lost master to its
        # decision (the takeover time, and how late the drone looked).
        "detection_s": (
            round(record.decided_at - record.lost_at, 6)
            if record.kind == drone_pb2.HANDOVER_KIND_TAKEOVER
            else None
        ),
        # A prepared handover (or one forced when its preparation ran out of
        # time): how long the preparation took, and what the target lacked.
        "prepare_s": (
            round(record.decided_at - record.prepare_started_at, 6)
            if record.prepare_started_at
            else None
        ),
        "prepare_timed_out": record.prepare_timed_out,
        "log_bytes": moved,
        "delay_s": round(record.delay_s, 6),
        "decided_at": record.decided_at,
        # The handover policy's why and where (trigger "policy").
        "reason": record.reason,
        "position": (
            [record.position.latitude_deg, record.position.longitude_deg]
            if record.HasField("position")
            else None
        ),
        "model_worst_case_s": round(
            t_max(
                config.flush_limit,
                largest_entry,
                hops,
                t_conn,
                link.latency,
                link.bandwidth,
            ),
            6,
        ),
    }


def _mission(
    snapshot: Snapshot,
    grid: int,
    plan: Plan | None,
    grid_mission: bool,
    targets: Sequence[tuple[float, float]] | None,
) -> dict[str, Any]:
    """What the mission was and what of it the drone executed."""
    audit = list(snapshot.drone.audit)
    pictures = sum(1 for a in audit if a.method == TAKE_PICTURE)
    gotos = sum(1 for a in audit if a.method == GOTO)
    survey = plan is None and grid_mission  # the grid or the corridor: a picture a waypoint
    return {
        "grid": grid if survey and targets is None else None,
        "plan": str(plan.path) if plan is not None else None,
        # The surveys check their position at every picture, so a picture is a
        # visit; the plan mission flies to each goto before the next. Of another
        # mission file only its gotos are known.
        "waypoints": (
            len(plan.waypoints)
            if plan is not None
            else (grid * grid if targets is None else len(targets))
            if grid_mission
            else gotos
        ),
        "waypoints_visited": pictures if survey else vehicle_gotos(snapshot, gotos),
        "pictures": pictures,
        "invocations": len(audit),
        "calls": max((c.reqnr for c in snapshot.controllers.values()), default=0),
        # When the drone received each TakePicture (wall clock), for
        # checking against the autopilot's own telemetry.
        "picture_requests": [
            {"reqnr": a.reqnr, "received_at": a.received_at}
            for a in audit
            if a.method == TAKE_PICTURE
        ],
    }


def vehicle_gotos(snapshot: Snapshot, requested: int) -> int:
    """The gotos the vehicle acted on, where it counted them (a goto the drone refused,
    or the vehicle did not take, visits nothing; a resume after a policy hold is the
    same leg again); else the ``requested`` gotos the drone's audit holds."""
    vehicle = snapshot.vehicle_effects
    if vehicle is None:
        return requested
    return len(_without_resumes([e for e in vehicle if e["effect"] == "goto"], snapshot))


def _setup(
    config: BatonConfig, drone: drone_pb2.DroneStatus, t_conn: float, largest_entry: int
) -> dict[str, Any]:
    """The ring, the links and the vehicle the mission ran with."""
    link = config.controller_link
    return {
        "controllers": len(config.controllers),
        "ring": config.ring_order,
        "initial_master": config.master_id,
        "flush_limit_bytes": config.flush_limit,
        "speedup": config.speedup,
        "controller_link": {"latency_s": link.latency, "bandwidth_bps": link.bandwidth},
        "t_conn_mean_s": round(t_conn, 6),
        "largest_entry_bytes": largest_entry,
        "vehicle": {
            "url": drone.vehicle_url,
            "autopilot": drone.flight_state.autopilot or "unknown",
            # MAVLink 2 signing on the drone's link (drone.mavlink_key), and
            # what it refused from the autopilot.
            "signing": drone.vehicle.signing,
            "refused_frames": drone.vehicle.refused_frames,
        },
    }


def _policy(config: BatonConfig, drone: drone_pb2.DroneStatus) -> dict[str, Any]:
    """The drone's handover policy and what it decided in the air."""
    decisions = drone.policy_decisions
    return {
        "name": label(
            drone_pb2.HandoverPolicy, drone.handover_policy or drone_pb2.HANDOVER_POLICY_NONE
        ),
        "radio_range": config.radio_range,
        # Holds in the air (a hold decided on the ground, before the controllers
        # are up or after the landing, stops nothing).
        "holds": sum(
            1
            for d in decisions
            if d.action == drone_pb2.POLICY_ACTION_HOLD and d.position.relative_altitude_m > 0.5
        ),
        "resumes": sum(1 for d in decisions if d.action == drone_pb2.POLICY_ACTION_RESUME),
        # No controller usable, flown on along a leg into a station's range.
        "flown_on": sum(
            1
            for d in decisions
            if d.action == drone_pb2.POLICY_ACTION_FLY_ON and d.position.relative_altitude_m > 0.5
        ),
    }


def _controller(cid: int, c: ring_pb2.ControllerStatus) -> dict[str, Any]:
    """One controller's final status."""
    return {
        "id": cid,
        "state": label(ring_pb2.ControllerState, c.state),
        "master": c.master,
        "reqnr": c.reqnr,
        "lognr": c.lognr,
        "log_bytes": c.log_bytes,
        "queue_length": c.queue_length,
        "mission": label(ring_pb2.MissionState, c.mission),
        "mission_error": c.mission_error,
        "invoked": c.invoked,
        "replayed": c.replayed,
        "reply_chain": c.reply_chain.hex(),
    }


def run_succeeded(report: dict[str, Any]) -> bool:
    """Completed, exactly once by the drone's audit and by the side effects counted
    (where they were), replicas consistent."""
    return bool(
        report["completed"]
        and report["exactly_once"]
        and report["side_effects"]["exactly_once"] is not False
        and report["replicas_consistent"]
    )


def _side_effects_line(effects: dict[str, Any]) -> str:
    """What the camera and the vehicle counted, in one line."""
    commands = effects["vehicle_commands"]
    vehicle = (
        ", ".join(f"{name} {n}" for name, n in commands.items())
        if isinstance(commands, dict)
        else commands
    )
    pictures = effects["pictures_taken"]
    camera = f"{pictures} pictures" if isinstance(pictures, int) else pictures
    return (
        f"side effects counted: camera {camera}; "
        f"vehicle {vehicle or 'nothing'}; exactly once: {effects['exactly_once']}"
    )


def _policy_lines(report: dict[str, Any]) -> list[str]:
    """The handover policy's part of the summary: masters and each handover's reason."""
    policy = report.get("policy") or {}
    if policy.get("name", "none") == "none":
        return []
    masters = " -> ".join(str(m) for m in report["masters"])
    lines = [
        f"handover policy {policy['name']}"
        f"{' with radio range' if policy['radio_range'] else ''}: masters {masters}; "
        f"holds {policy['holds']}, resumes {policy['resumes']}, "
        f"flown on {policy.get('flown_on', 0)}"
    ]
    lines += [
        f"  {h['from']} -> {h['to']} after {h['after_reqnr']}: {h['reason']}"
        for h in report["handovers"]
        if h["trigger"] == "policy"
    ]
    return lines


# The handover table's columns, in the terminal's summary and the HTML report.
HANDOVER_COLUMNS = (
    "handover",
    "from",
    "to",
    "after",
    "hops",
    "log bytes",
    "delay s",
    "model s",
    "kind",
)


_WIDTHS = (8, 4, 3, 6, 4, 10, 8, 8)  # the terminal's, of the columns before "kind"


def handover_cells(number: int, h: dict[str, Any]) -> list[str]:
    """Handover ``number`` of the report (``h``) as the handover table's cells."""
    kind = h.get("kind") or "cooperative"
    if kind == "takeover":
        kind += f" ({h['trigger']}, detected after {h['detection_s']:.3f} s)"
    elif h.get("prepare_s") is not None:
        what = "preparation timed out" if h["prepare_timed_out"] else "prepared"
        kind += f" ({what} in {h['prepare_s']:.3f} s)"
    return [
        str(number),
        str(h["from"]),
        str(h["to"]),
        str(h["after_reqnr"]),
        str(h["hops"]),
        str(h["log_bytes"]),
        f"{h['delay_s']:.3f}",
        f"{h['model_worst_case_s']:.3f}",
        kind,
    ]


def summary_table(report: dict[str, Any]) -> str:
    """The report as a few aligned tables for the terminal."""
    mission = report["mission"]
    drone = report["drone"]
    lines = [
        f"mission {'COMPLETED' if report['completed'] else 'NOT COMPLETED'} in "
        f"{report['duration_s']:.1f} s: {mission['waypoints_visited']}/{mission['waypoints']} "
        f"waypoints, {mission['pictures']} pictures, {mission['invocations']} invocations",
        f"drone: executed {drone['executed']}, duplicates {drone['duplicates']}, "
        f"rejected {drone['rejected']}; exactly once: {report['exactly_once']}; "
        f"replicas consistent: {report['replicas_consistent']}",
        _side_effects_line(report["side_effects"]),
        *(f"  {problem}" for problem in report["side_effects"]["problems"]),
        *_policy_lines(report),
        "",
        " ".join(f"{c:>{w}}" for c, w in zip(HANDOVER_COLUMNS[:-1], _WIDTHS, strict=True))
        + f"  {HANDOVER_COLUMNS[-1]}",
    ]
    for k, h in enumerate(report["handovers"], start=1):
        *numbers, kind = handover_cells(k, h)
        aligned = " ".join(f"{c:>{w}}" for c, w in zip(numbers, _WIDTHS, strict=True))
        lines.append(f"{aligned}  {kind}")
    for missed in report["handovers_missed"]:
        lines.append(
            f"  planned handover {missed[0]}:{missed[1]} did not happen (mission too short?)"
        )
    lines += [
        "",
        f"{'controller':>10} {'state':>8} {'master':>6} {'reqnr':>6} {'lognr':>6} {'replayed':>8} "
        f"{'invoked':>7} {'mission':>8}",
    ]
    for c in report["controllers"]:
        lines.append(
            f"{c['id']:>10} {c['state']:>8} {'yes' if c['master'] else 'no':>6} {c['reqnr']:>6} "
            f"{c['lognr']:>6} {c['replayed']:>8} {c['invoked']:>7} {c['mission']:>8}"
        )
        if c["mission_error"]:
            lines.append(f"{'':>10} error: {c['mission_error']}")
    if "waits" in report:  # the run's waits (Progress's WaitLog): quiet, then loud
        lines += ["", *report_lines(report["waits"])]
    return "\n".join(lines)
