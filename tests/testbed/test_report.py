"""The report's side-effect check, fed chosen effects: it catches what it must.

The end-to-end tests show it agrees with real runs; these show it can fail:
a goto or a picture done twice, a second takeoff, a goto out of order, each
makes ``exactly_once`` false with a problem that says what happened.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from baton.config import parse_config
from baton.missions.grid import waypoints
from baton.sdk import Position, offset
from baton.testbed.local import MissionPlan, Snapshot, TestbedPlan
from baton.testbed.report import (
    GOTO,
    NOT_COUNTED,
    build_report,
    check_side_effects,
    run_succeeded,
    summary_table,
)
from baton.v1 import drone_pb2, ring_pb2

ORIGIN = Position(47.397742, 8.545594, 488.0, 0.0)
GRID, SPACING_M = 3, 20.0


def grid_vehicle_effects(grid: int = GRID, spacing_m: float = SPACING_M) -> list[dict[str, Any]]:
    """What the sim vehicle counts for the grid mission flown once, as MAVSDK drives it."""
    effects: list[dict[str, Any]] = [
        {"effect": "arm"},
        {"effect": "takeoff", "relative_altitude_m": 5.0},
        {"effect": "set_speed", "speed_m_s": 5.0},
    ]
    for north, east in waypoints(grid, spacing_m):
        target = offset(ORIGIN, north, east)
        effects.append(
            {
                "effect": "goto",
                # As it crosses MAVLink: 1e-7 degrees.
                "latitude_deg": round(target.latitude_deg * 1e7) / 1e7,
                "longitude_deg": round(target.longitude_deg * 1e7) / 1e7,
                "altitude_amsl_m": 493.0,
            }
        )
        effects.append({"effect": "set_speed", "speed_m_s": 5.0})
    effects.append({"effect": "land"})
    return numbered(effects)


def numbered(effects: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{"seq": k, "time": 1e9 + k, **e} for k, e in enumerate(effects, start=1)]


def pictures(n: int) -> list[dict[str, Any]]:
    return numbered([{"effect": "picture", "resolution": "640x546", "bytes": 1048335}] * n)


def snapshot(vehicle: list[dict[str, Any]] | None, camera: list[dict[str, Any]] | None) -> Snapshot:
    return Snapshot(drone_pb2.DroneStatus(), vehicle_effects=vehicle, camera_effects=camera)


@pytest.mark.parametrize("spacing_m", [SPACING_M, None], ids=["spacing-given", "inferred"])
def test_a_grid_flown_once_is_exactly_once(spacing_m: float | None) -> None:
    checked = check_side_effects(snapshot(grid_vehicle_effects(), pictures(9)), GRID, spacing_m)
    assert checked == {
        "pictures_taken": 9,
        "pictures_expected": 9,
        "vehicle_commands": {"arm": 1, "goto": 9, "land": 1, "set_speed": 10, "takeoff": 1},
        "problems": [],
        "exactly_once": True,
    }


@pytest.mark.parametrize("spacing_m", [SPACING_M, None], ids=["spacing-given", "inferred"])
@pytest.mark.parametrize("twice", [1, 4], ids=["first-goto", "fourth-goto"])
def test_a_goto_acted_on_twice_is_caught(spacing_m: float | None, twice: int) -> None:
    effects = grid_vehicle_effects()
    gotos = [k for k, e in enumerate(effects) if e["effect"] == "goto"]
    where = gotos[twice - 1]
    effects.insert(where + 1, dict(effects[where]))  # the drone re-executed that Goto
    checked = check_side_effects(snapshot(numbered(effects), pictures(9)), GRID, spacing_m)
    assert checked["exactly_once"] is False
    assert checked["vehicle_commands"]["goto"] == 10
    problems = " | ".join(checked["problems"])
    assert "a goto to" in problems and "2 times" in problems, problems
    assert "10 gotos; the 3x3 grid has 9 waypoints" in problems
    assert f"goto {twice + 1} flew to" in problems


def test_a_picture_taken_twice_is_caught() -> None:
    checked = check_side_effects(snapshot(grid_vehicle_effects(), pictures(10)), GRID)
    assert checked["exactly_once"] is False
    assert checked["problems"] == ["the camera produced 10 pictures; the 3x3 grid takes 9"]


def test_a_second_takeoff_is_caught() -> None:
    effects = grid_vehicle_effects()
    effects.insert(2, {"effect": "takeoff", "relative_altitude_m": 5.0})
    checked = check_side_effects(snapshot(numbered(effects), pictures(9)), GRID)
    assert checked["exactly_once"] is False
    assert checked["problems"] == ["the vehicle acted on 2 takeoff commands, not 1"]


def test_gotos_out_of_order_are_caught() -> None:
    effects = grid_vehicle_effects()
    gotos = [k for k, e in enumerate(effects) if e["effect"] == "goto"]
    effects[gotos[2]], effects[gotos[3]] = effects[gotos[3]], effects[gotos[2]]
    checked = check_side_effects(snapshot(numbered(effects), pictures(9)), GRID, SPACING_M)
    assert checked["exactly_once"] is False
    assert checked["problems"] == ["goto 3 flew to 20.0 m from waypoint 3 of the grid"]


def test_a_part_that_counts_nothing_is_not_counted_and_not_held_against_the_run() -> None:
    remote_line = summary_table(
        {
            "completed": True,
            "duration_s": 1.0,
            "mission": {"waypoints_visited": 9, "waypoints": 9, "pictures": 9, "invocations": 1},
            "drone": {"executed": 1, "duplicates": 0, "rejected": 0},
            "exactly_once": True,
            "replicas_consistent": True,
            "side_effects": check_side_effects(snapshot(None, None), GRID),
            "handovers": [],
            "handovers_missed": [],
            "controllers": [],
        }
    ).splitlines()[2]
    assert remote_line == (
        "side effects counted: camera not counted; vehicle not counted; exactly once: None"
    )
    sitl = check_side_effects(snapshot(None, pictures(9)), GRID)
    assert sitl["vehicle_commands"] == NOT_COUNTED
    assert sitl["exactly_once"] is True
    remote = check_side_effects(snapshot(None, None), GRID)
    assert remote["pictures_taken"] == remote["vehicle_commands"] == NOT_COUNTED
    assert remote["exactly_once"] is None


def test_the_report_fails_a_run_whose_audit_is_clean_but_a_goto_flew_twice() -> None:
    """The drone's audit and the controllers agree; only the vehicle saw the double goto."""
    config = parse_config({"controllers": [{"id": 0, "address": "127.0.0.1:7100"}]})
    effects = grid_vehicle_effects()
    effects.insert(4, dict(effects[3]))
    run = snapshot(numbered(effects), pictures(9))
    run.controllers[0] = ring_pb2.ControllerStatus(
        id=0, mission=ring_pb2.MISSION_STATE_DONE, master=True
    )
    report = build_report(config, run, GRID, 1.0, [], SPACING_M)
    assert report["completed"] and report["exactly_once"] and report["replicas_consistent"]
    assert report["side_effects"]["exactly_once"] is False
    assert not run_succeeded(report)
    table = summary_table(report)
    assert "side effects counted: camera 9 pictures; vehicle arm 1, goto 10," in table
    assert "exactly once: False" in table and "2 times" in table
    report["side_effects"] = check_side_effects(snapshot(grid_vehicle_effects(), None), GRID)
    assert run_succeeded(report)


def test_a_takeover_is_reported_as_one_and_does_not_stand_for_a_planned_handover() -> None:
    """Two scripted handovers planned; the drone did the first and took the master over
    once (lost): the report lists both with their kind, the takeover with its detection
    time, the table and the missed list say the second planned handover never came."""
    config = parse_config(
        {"controllers": [{"id": i, "address": f"127.0.0.1:{7100 + i}"} for i in range(3)]}
    )
    drone = drone_pb2.DroneStatus()
    drone.handovers.add(
        old_master=0,
        new_master=1,
        after_reqnr=90,
        trigger=drone_pb2.HANDOVER_TRIGGER_SCRIPT,
        kind=drone_pb2.HANDOVER_KIND_COOPERATIVE,
        decided_at=100.0,
        delay_s=0.2,
    )
    drone.handovers.add(
        old_master=1,
        new_master=2,
        after_reqnr=120,
        trigger=drone_pb2.HANDOVER_TRIGGER_LOST,
        kind=drone_pb2.HANDOVER_KIND_TAKEOVER,
        decided_at=110.0,
        lost_at=109.0,
        delay_s=0.6,
    )
    run = Snapshot(drone, vehicle_effects=None, camera_effects=None)
    for cid in range(3):
        run.controllers[cid] = ring_pb2.ControllerStatus(
            id=cid, mission=ring_pb2.MISSION_STATE_DONE
        )
    report = build_report(config, run, GRID, 1.0, [(90, 1), (180, 2)], SPACING_M)
    assert [(h["kind"], h["trigger"]) for h in report["handovers"]] == [
        ("cooperative", "script"),
        ("takeover", "lost"),
    ]
    assert report["handovers"][0]["detection_s"] is None
    assert report["handovers"][1]["detection_s"] == pytest.approx(1.0)
    assert report["handovers_missed"] == [[180, 2]]
    table = summary_table(report)
    assert "takeover" in table and "planned handover 180:2 did not happen" in table


def test_gotos_the_vehicle_did_not_act_on_visit_nothing() -> None:
    """A mission file's seven Gotos, all refused: the drone audited them (a refused
    request keeps its number), the vehicle acted on none, so none was visited."""
    config = parse_config({"controllers": [{"id": 0, "address": "127.0.0.1:7100"}]})
    drone = drone_pb2.DroneStatus()
    for reqnr in range(1, 8):
        drone.audit.add(reqnr=reqnr, method=GOTO, controller_id=0)
    refused = Snapshot(drone, vehicle_effects=numbered([{"effect": "arm"}]), camera_effects=[])
    mission = build_report(config, refused, GRID, 1.0, [], grid_mission=False)["mission"]
    assert (mission["waypoints_visited"], mission["waypoints"]) == (0, 7)
    # Where the vehicle counts nothing (SITL, an autopilot of its own), the audit is all
    # there is.
    uncounted = Snapshot(drone, vehicle_effects=None, camera_effects=None)
    mission = build_report(config, uncounted, GRID, 1.0, [], grid_mission=False)["mission"]
    assert mission["waypoints_visited"] == 7


@pytest.mark.parametrize(
    ("plan", "shown"),
    [
        (TestbedPlan(), "5x5 grid"),
        (TestbedPlan(mission=MissionPlan(kind="corridor")), "corridor of 1500 m"),
        (TestbedPlan(mission_file=Path("missions/square.py")), "mission square.py"),
        (
            TestbedPlan(mission_file=Path("plan.py"), flight_plan=Path("/x/survey.plan")),
            "plan survey.plan",
        ),
    ],
)
def test_the_banner_names_the_mission_flown(plan: TestbedPlan, shown: str) -> None:
    assert plan.describe_mission() == shown
