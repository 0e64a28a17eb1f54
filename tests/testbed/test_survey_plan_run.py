"""One real testbed run of examples/survey.plan through three handovers, then what it
leaves: the plan flown exactly once as the vehicle and the camera counted it, the drone's
.tlog read back by pymavlink's mavlogdump.py, and the controllers' logs checked by
`baton replay` against the mission as flown, edited to diverge, and edited harmlessly."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
from helpers.testbed_runs import baton_run, fly_plan

from baton.controller.history import read_log
from baton.missions import plan as plan_mission
from baton.v1 import drone_api_pb2 as api

REPO = Path(__file__).resolve().parents[2]
SURVEY = REPO / "examples" / "survey.plan"
PLAN_MISSION = Path(plan_mission.__file__)
HANDOVERS = ("12:1", "30:2", "50:0")


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """`baton testbed --mission examples/survey.plan` to the end; its report and stdout."""
    return fly_plan(tmp_path_factory.mktemp("survey"), SURVEY, HANDOVERS)


def test_the_survey_plan_is_flown_exactly_once_through_handovers(run: dict[str, Any]) -> None:
    plan = plan_mission.load_plan(str(SURVEY))
    assert run["completed"] and run["exactly_once"] and run["replicas_consistent"]
    assert len(run["handovers"]) == len(HANDOVERS) and run["handovers_missed"] == []
    assert run["mission"]["plan"] == str(SURVEY)
    assert run["mission"]["waypoints"] == run["mission"]["waypoints_visited"] == 8
    effects = run["side_effects"]
    assert effects["exactly_once"] is True and effects["problems"] == [], effects
    # Counted by the camera and the sim vehicle, not by the drone's audit.
    assert effects["pictures_taken"] == effects["pictures_expected"] == plan.pictures == 7
    commands = effects["vehicle_commands"]
    assert commands["arm"] == commands["takeoff"] == 1 and commands["goto"] == 8
    assert "side effects counted: camera 7 pictures" in run["stdout"]
    # Controllers of every mastership flew part of it.
    assert {h["to"] for h in run["handovers"]} == {0, 1, 2}


def test_the_goto_targets_are_the_plans_waypoints_in_order(run: dict[str, Any]) -> None:
    workdir = Path(run["files"]["workdir"])
    gotos = [
        json.loads(line)
        for line in (workdir / "vehicle-effects.jsonl").read_text().splitlines()
        if '"goto"' in line
    ]
    plan = plan_mission.load_plan(str(SURVEY))
    assert [(round(g["latitude_deg"], 6), round(g["longitude_deg"], 6)) for g in gotos] == [
        (round(w.latitude_deg, 6), round(w.longitude_deg, 6)) for w in plan.waypoints
    ]
    climbs = [round(g["altitude_amsl_m"] - gotos[0]["altitude_amsl_m"], 1) for g in gotos]
    assert climbs == [round(w.altitude_m - plan.waypoints[0].altitude_m, 1) for w in plan.waypoints]


def test_the_drones_tlog_reads_back_with_mavlogdump(run: dict[str, Any]) -> None:
    tlogs = run["files"]["tlogs"]
    assert len(tlogs) == 1 and Path(tlogs[0]).stat().st_size > 0
    assert f"telemetry log (.tlog): {tlogs[0]}" in run["stdout"]
    mavlogdump = Path(sys.executable).parent / "mavlogdump.py"
    dump = subprocess.run(
        [sys.executable, str(mavlogdump), "--types", "HEARTBEAT,GLOBAL_POSITION_INT", tlogs[0]],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert dump.returncode == 0, dump.stderr
    kinds = Counter(re.findall(r"^\S+ \S+: (\w+) ", dump.stdout, re.MULTILINE))
    assert kinds["HEARTBEAT"] > 10 and kinds["GLOBAL_POSITION_INT"] > 10, kinds
    # The run's flight is in it: the vehicle climbed to the survey's 10 m (mm above home).
    relative = [int(m) for m in re.findall(r"relative_alt : (-?\d+)", dump.stdout)]
    assert max(relative) > 9_000
    # Both ways: MAVSDK's own heartbeats (a ground station, type 6) went to the autopilot.
    assert re.search(r"HEARTBEAT \{type : 6,", dump.stdout)


def replay(run: dict[str, Any], mission: Path, plan: Path) -> subprocess.CompletedProcess[str]:
    return baton_run(
        "replay",
        run["files"]["workdir"],
        "--mission",
        str(mission),
        "--mission-arg",
        f"plan={plan}",
        timeout=120,
    )


def test_the_logs_replay_clean_against_the_mission_as_flown(run: dict[str, Any]) -> None:
    mission = run["files"]["mission"]
    assert mission["file"] == str(PLAN_MISSION) and mission["args"] == [f"plan={SURVEY}"]
    assert f"replay them: baton replay {run['files']['workdir']}" in run["stdout"]
    result = replay(run, PLAN_MISSION, SURVEY)
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.splitlines()[-1] == "3 clean, 0 diverged, 0 unreadable"


def test_a_harmless_edit_replays_clean(run: dict[str, Any], tmp_path: Path) -> None:
    source = PLAN_MISSION.read_text()
    edited = source.replace('print(f"plan complete: {flight.pictures} pictures", flush=True)', "")
    edited = edited.replace(
        "def _relative(item: Item, home: Position) -> float:",
        (
            "# edited: a comment, a print gone, a helper renamed\n"
            "def _relative(item: Item, home: Position) -> float:"
        ),
    )
    assert edited != source
    mission = tmp_path / "plan_edited.py"
    mission.write_text(edited)
    result = replay(run, mission, SURVEY)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "3 clean, 0 diverged" in result.stdout


def test_a_plan_edited_to_diverge_is_caught_at_its_goto(
    run: dict[str, Any], tmp_path: Path
) -> None:
    document = json.loads(SURVEY.read_text())
    item = document["mission"]["items"][4]  # the waypoint after the survey, at 8 m
    assert item["command"] == 16 and item["params"][6] == 8
    item["params"][6] = 9
    edited = tmp_path / "survey_edited.plan"
    edited.write_text(json.dumps(document))
    # Where the log holds that goto: the request number the replay must name.
    log = Path(run["files"]["controller_logs"]["1"])
    gotos = [
        (entry.reqnr, api.GotoRequest.FromString(entry.request))
        for message in read_log(log)
        for entry in message.entries
        if entry.method == "/baton.v1.Mobility/Goto"
    ]
    reqnr, logged = next((n, g) for n, g in gotos if g.relative_altitude_m == 8.0)
    result = replay(run, PLAN_MISSION, edited)
    assert result.returncode == 1, result.stdout + result.stderr
    assert result.stdout.count(f"diverged at request {reqnr}: ") == 3
    where = f"latitude_deg: {logged.latitude_deg!r} longitude_deg: {logged.longitude_deg!r}"
    assert f"the log holds:    Mobility.Goto {{{where} relative_altitude_m: 8.0}}" in result.stdout
    assert f"the program asks: Mobility.Goto {{{where} relative_altitude_m: 9.0}}" in (
        result.stdout
    )
    assert "fields that differ: relative_altitude_m" in result.stdout
    assert result.stdout.splitlines()[-1] == "0 clean, 3 diverged, 0 unreadable"


def test_an_unsupported_item_is_refused_before_anything_starts(tmp_path: Path) -> None:
    document = json.loads(SURVEY.read_text())
    document["mission"]["items"].insert(
        2,
        {"type": "SimpleItem", "command": 115, "frame": 2, "params": [90, 0, 1, 0, 0, 0, 0]},
    )
    bad = tmp_path / "yaw.plan"
    bad.write_text(json.dumps(document))
    result = baton_run(
        "testbed", "--mission", str(bad), "--workdir", str(tmp_path / "w"), timeout=60
    )
    assert result.returncode == 2
    assert "item 2: CONDITION_YAW (115) is not supported" in result.stderr
    assert not (tmp_path / "w" / "testbed.yaml").exists()  # nothing was started


def test_a_mission_edited_to_diverge_is_caught_at_its_takeoff(
    run: dict[str, Any], tmp_path: Path
) -> None:
    source = PLAN_MISSION.read_text()
    edited = source.replace(
        "drone.mobility.takeoff(flight_plan.takeoff_altitude_m)",
        "drone.mobility.takeoff(flight_plan.takeoff_altitude_m + 1)",
    )
    assert edited != source
    mission = tmp_path / "plan_higher.py"
    mission.write_text(edited)
    log = Path(run["files"]["controller_logs"]["0"])
    (reqnr,) = [
        entry.reqnr
        for message in read_log(log)
        for entry in message.entries
        if entry.method == "/baton.v1.Mobility/Takeoff"
    ]
    result = replay(run, mission, SURVEY)
    assert result.returncode == 1, result.stdout + result.stderr
    assert result.stdout.count(f"replayed {reqnr - 1} of ") == 3
    assert result.stdout.count(f"diverged at request {reqnr}: ") == 3
    assert "the log holds:    Mobility.Takeoff {altitude_m: 10.0}" in result.stdout
    assert "the program asks: Mobility.Takeoff {altitude_m: 11.0}" in result.stdout
