"""Reading and checking QGroundControl plans (baton/missions/plan.py), no flight."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from baton.missions.plan import (
    DO_SET_CAM_TRIGG_DIST,
    IMAGE_START_CAPTURE,
    NAV_WAYPOINT,
    PlanError,
    load_plan,
)

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def simple(command: int, params: list[Any], frame: int = 3) -> dict[str, Any]:
    return {"type": "SimpleItem", "command": command, "frame": frame, "params": params}


def plan_file(tmp_path: Path, items: list[dict[str, Any]], name: str = "p.plan") -> str:
    path = tmp_path / name
    document = {"fileType": "Plan", "version": 1, "mission": {"items": items, "hoverSpeed": 3}}
    path.write_text(json.dumps(document))
    return str(path)


TAKEOFF = simple(22, [0, 0, 0, None, 47.0, 8.0, 15])
WAYPOINT = simple(16, [0, 0, 0, None, 47.0001, 8.0, 20])


def test_the_shipped_examples_read_as_qgroundcontrol_writes_them() -> None:
    survey = load_plan(str(EXAMPLES / "survey.plan"))
    assert survey.takeoff_altitude_m == 10 and survey.end == "return_to_launch"
    assert survey.cruise_speed_m_s == 5
    assert len(survey.waypoints) == 8 and survey.pictures == 7
    assert survey.items[2].where == "item 3 (survey), its item 0"
    square = load_plan(str(EXAMPLES / "square.waypoints"))
    # Item 0 of a QGC WPL file is home and is not flown.
    assert [i.where for i in square.waypoints] == ["item 2", "item 4", "item 6"]
    assert square.takeoff_altitude_m == 8 and square.end == "land" and square.pictures == 3


def test_a_survey_without_stored_items_is_expanded_from_its_transects(tmp_path: Path) -> None:
    transects = [[47.0, 8.0], [47.0, 8.0004], [47.0002, 8.0004], [47.0002, 8.0]]  # ~30 m rows

    def survey(hover: bool) -> dict[str, Any]:
        return {
            "type": "ComplexItem",
            "complexItemType": "survey",
            "Altitude": 12,
            "TransectStyleComplexItem": {
                "HoverAndCapture": hover,
                "VisualTransectPoints": transects,
                "CameraCalc": {"AdjustedFootprintFrontal": 10, "DistanceToSurface": 12},
            },
        }

    hovering = load_plan(plan_file(tmp_path, [TAKEOFF, survey(True)]))
    # 30.3 m rows, a picture every 10 m from the entry: 4 a row.
    assert hovering.pictures == 8 and len(hovering.waypoints) == 8
    assert all(w.altitude_m == 12 for w in hovering.waypoints)
    assert [i.command for i in hovering.items[:2]] == [NAV_WAYPOINT, IMAGE_START_CAPTURE]
    by_distance = load_plan(plan_file(tmp_path, [TAKEOFF, survey(False)]))
    assert by_distance.pictures is None  # where the polls fall
    triggers = [i.params[0] for i in by_distance.items if i.command == DO_SET_CAM_TRIGG_DIST]
    assert triggers == [10, 0, 10, 0]


@pytest.mark.parametrize(
    ("items", "message"),
    [
        (
            [TAKEOFF, WAYPOINT, simple(115, [90, 0, 1, 0, 0, 0, 0], 2)],
            "item 2: CONDITION_YAW (115) is not supported; a plan may use NAV_WAYPOINT (16)",
        ),
        ([TAKEOFF, simple(4242, [0] * 7, 2)], "item 1: MAV_CMD (4242) is not supported"),
        (
            [
                TAKEOFF,
                {
                    "type": "ComplexItem",
                    "complexItemType": "survey",
                    "TransectStyleComplexItem": {"Items": [WAYPOINT, simple(2500, [0] * 7, 2)]},
                },
            ],
            "item 1 (survey), its item 1: VIDEO_START_CAPTURE (2500) is not supported",
        ),
        (
            [TAKEOFF, {"type": "ComplexItem", "complexItemType": "StructureScan"}],
            "item 1: complex item 'StructureScan' is not flown",
        ),
        (
            [TAKEOFF, simple(2000, [0, 2, 0, 0, 0, 0, 0], 2)],
            "item 1: IMAGE_START_CAPTURE (2000) with param3 (total images) 0",
        ),
        ([WAYPOINT, TAKEOFF], "item 1: NAV_TAKEOFF (22) must be the plan's first item"),
        (
            [TAKEOFF, simple(20, [0] * 7, 2), WAYPOINT],
            "item 1: NAV_RETURN_TO_LAUNCH (20) must be the plan's last item",
        ),
        ([TAKEOFF, simple(16, [0, 0, 0, 0, 47, 8, 20], 10)], "item 1: NAV_WAYPOINT (16): frame 10"),
        ([TAKEOFF, {"type": "SimpleItem", "command": 16}], "item 1: 'params' must be a list"),
    ],
)
def test_what_cannot_be_flown_is_refused_by_index_and_name(
    tmp_path: Path, items: list[dict[str, Any]], message: str
) -> None:
    with pytest.raises(PlanError) as refused:
        load_plan(plan_file(tmp_path, items))
    assert message in str(refused.value)


def test_bad_files_say_what_they_are_not(tmp_path: Path) -> None:
    (tmp_path / "x.plan").write_text("{not json")
    with pytest.raises(PlanError, match=r"neither a QGroundControl \.plan"):
        load_plan(str(tmp_path / "x.plan"))
    (tmp_path / "y.waypoints").write_text("QGC WPL 110\n1 0 3 16 0 0 0\n")
    with pytest.raises(PlanError, match="line 2: 7 fields; a waypoint line has 12"):
        load_plan(str(tmp_path / "y.waypoints"))
    with pytest.raises(PlanError, match="cannot read it"):
        load_plan(str(tmp_path / "none.plan"))
    with pytest.raises(PlanError, match="no plan given: pass plan=FILE"):
        load_plan("")


def test_the_checker_command_prints_the_steps_or_the_refusal(tmp_path: Path) -> None:
    ok = subprocess.run(
        [sys.executable, "-m", "baton.missions.plan", str(EXAMPLES / "survey.plan")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert ok.returncode == 0 and "8 waypoints, 7 pictures" in ok.stdout
    bad = plan_file(tmp_path, [TAKEOFF, simple(115, [0] * 7, 2)])
    refused = subprocess.run(
        [sys.executable, "-m", "baton.missions.plan", bad], capture_output=True, text=True
    )
    assert refused.returncode == 1 and "item 1: CONDITION_YAW (115)" in refused.stderr
