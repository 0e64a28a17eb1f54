"""One real testbed run of examples/inspection.plan (a region of interest, a spline
waypoint, a DO_JUMP loop and delays) through three handovers, checked where the effects
happen: the sim vehicle's gotos and regions of interest in the plan's order, each loop
lap's, the camera's pictures with where they looked, the delays in the log, and `baton
replay` of the run clean."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
from helpers.testbed_runs import baton_run, fly_plan

from baton.controller.history import read_log
from baton.effects import read_effects
from baton.missions import plan as plan_mission
from baton.v1 import drone_api_pb2 as api

REPO = Path(__file__).resolve().parents[2]
INSPECTION = REPO / "examples" / "inspection.plan"
PLAN_MISSION = Path(plan_mission.__file__)
HANDOVERS = ("12:1", "40:2", "70:0")


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """`baton testbed --mission examples/inspection.plan` to the end; its report."""
    return fly_plan(tmp_path_factory.mktemp("inspection"), INSPECTION, HANDOVERS)


def vehicle_effects(run: dict[str, Any]) -> list[dict[str, Any]]:
    return read_effects(Path(run["files"]["workdir"]) / "vehicle-effects.jsonl")


def test_the_plan_is_flown_exactly_once_through_handovers(run: dict[str, Any]) -> None:
    assert run["completed"] and run["exactly_once"] and run["replicas_consistent"]
    assert len(run["handovers"]) == len(HANDOVERS) and run["handovers_missed"] == []
    assert {h["to"] for h in run["handovers"]} == {0, 1, 2}
    effects = run["side_effects"]
    # The report's own check: arm, takeoff, RTL once; the gotos and ROIs in order.
    assert effects["exactly_once"] is True and effects["problems"] == [], effects
    commands = effects["vehicle_commands"]
    assert commands["roi"] == 4 and commands["roi_none"] == 1 and commands["goto"] == 7


def test_the_vehicle_flew_each_lap_and_pointed_the_gimbal_where_the_plan_says(
    run: dict[str, Any],
) -> None:
    plan = plan_mission.load_plan(str(INSPECTION))
    acted = [e for e in vehicle_effects(run) if e["effect"] in ("goto", "roi", "roi_none")]
    assert [e["effect"] for e in acted] == [name for name, _ in plan.vehicle_steps]
    home_amsl = 488.0  # the testbed's home
    for effect, (name, item) in zip(acted, plan.vehicle_steps, strict=True):
        if name == "roi_none":
            continue
        assert (round(effect["latitude_deg"], 6), round(effect["longitude_deg"], 6)) == (
            round(item.latitude_deg, 6),
            round(item.longitude_deg, 6),
        ), item.where
        if name == "roi":  # its altitude above home, as the plan gives it
            assert effect["altitude_amsl_m"] == pytest.approx(home_amsl + item.altitude_m)
    # The DO_JUMP was taken twice: the loop's waypoints were each flown three times.
    (jump,) = plan.jumps
    gotos = [e for e in acted if e["effect"] == "goto"]
    laps = Counter((round(e["latitude_deg"], 6), round(e["longitude_deg"], 6)) for e in gotos)
    loop = [i for i in plan.waypoints if i.lap == jump.repeat + 1]
    assert [i.where for i in loop] == ["item 3", "item 6"]
    for item in loop:
        where = (round(item.latitude_deg, 6), round(item.longitude_deg, 6))
        assert laps[where] == jump.repeat + 1, item.where


def test_each_picture_records_where_it_looked(run: dict[str, Any]) -> None:
    pictures = read_effects(Path(run["files"]["workdir"]) / "camera-effects.jsonl")
    looked = [
        (p.get("looking_at_latitude_deg"), p.get("looking_at_longitude_deg")) for p in pictures
    ]
    structure = (47.39782, 8.54575)  # the plan's region of interest
    # Three in the loop with the ROI set, the last after it was cleared.
    assert looked == [structure, structure, structure, (None, None)]


def test_the_delays_are_the_mission_clocks_logged_sleeps(run: dict[str, Any]) -> None:
    master = str(run["handovers"][-1]["to"])
    sleeps = [
        api.SleepRequest.FromString(entry.request).seconds
        for message in read_log(Path(run["files"]["controller_logs"][master]))
        for entry in message.entries
        if entry.method == "/baton.v1.Clock/Sleep"
    ]
    # CONDITION_DELAY 2 s on each of three laps (the position polls sleep 1 s).
    assert sleeps.count(2.0) == 3


def test_the_logs_replay_clean(run: dict[str, Any]) -> None:
    result = baton_run(
        "replay",
        run["files"]["workdir"],
        "--mission",
        str(PLAN_MISSION),
        "--mission-arg",
        f"plan={INSPECTION}",
        timeout=120,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.splitlines()[-1] == "3 clean, 0 diverged, 0 unreadable"


def test_a_plan_edited_to_loop_once_more_diverges(run: dict[str, Any], tmp_path: Path) -> None:
    document = json.loads(INSPECTION.read_text())
    (jump,) = [i for i in document["mission"]["items"] if i["command"] == 177]
    jump["params"][1] += 1
    edited = tmp_path / "inspection_more.plan"
    edited.write_text(json.dumps(document))
    result = baton_run(
        "replay",
        run["files"]["workdir"],
        "--mission",
        str(PLAN_MISSION),
        "--mission-arg",
        f"plan={edited}",
        timeout=120,
    )
    assert result.returncode == 1, result.stdout + result.stderr
    assert result.stdout.splitlines()[-1] == "0 clean, 3 diverged, 0 unreadable"


@pytest.mark.parametrize(
    ("end", "effect"), [("", ("set_mode", "HOLD")), ("end=land", ("land", None))]
)
def test_an_open_ended_plan_ends_as_the_run_chose(
    tmp_path: Path, end: str, effect: tuple[str, str | None]
) -> None:
    takeoff = {
        "type": "SimpleItem",
        "command": 22,
        "frame": 3,
        "params": [0, 0, 0, None, 47.397742, 8.545594, 8],
    }
    waypoint = {
        "type": "SimpleItem",
        "command": 16,
        "frame": 3,
        "params": [0, 0, 0, None, 47.3979, 8.545594, 8],
    }
    plan = tmp_path / "open.plan"
    plan.write_text(json.dumps({"fileType": "Plan", "mission": {"items": [takeoff, waypoint]}}))
    chosen = ["--mission-arg", end] if end else []
    report = tmp_path / "report.json"
    result = baton_run(
        "testbed",
        "--mission",
        str(plan),
        *chosen,
        "--speedup",
        "20",
        "--handover",
        "8:1",
        "--workdir",
        str(tmp_path / "w"),
        "--report",
        str(report),
    )
    assert result.returncode == 0, result.stdout + result.stderr
    effects = json.loads(report.read_text())["side_effects"]
    assert effects["exactly_once"] is True and effects["problems"] == [], effects
    ends = [
        e
        for e in read_effects(tmp_path / "w" / "vehicle-effects.jsonl")
        if e["effect"] in ("set_mode", "land", "return_to_launch")
    ]
    assert [(e["effect"], e.get("mode")) for e in ends] == [effect]
