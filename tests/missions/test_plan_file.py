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
            "item 2: CONDITION_YAW (115) is not supported: the drone API has no call that does "
            "it. Remove it from the plan; a plan may use NAV_WAYPOINT (16)",
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
    assert refused.stderr.endswith("\n")  # the refusal ends its line


# The items QGroundControl writes for inspection plans (issue 35) ---------------------------

STRUCTURE = [0, 0, 0, 0, 47.00005, 8.0001, 2]
SPLINE = simple(82, [0, 0, 0, 0, 47.0002, 8.0, 20])


def numbered(items: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """``items`` with QGroundControl's doJumpId: 1, 2, ... (home is 0)."""
    return [{**item, "doJumpId": k} for k, item in enumerate(items, start=1)]


def test_the_shipped_inspection_plan_is_flown_item_by_item() -> None:
    plan = load_plan(str(EXAMPLES / "inspection.plan"))
    steps = [(name, item.where, item.lap) for name, item in plan.vehicle_steps]
    loop = [("goto", "item 3", 1), ("roi", "item 4", 1), ("goto", "item 6", 1)]
    assert steps == [
        ("goto", "item 1", 1),
        ("roi", "item 2", 1),
        *loop,
        *[(n, w, 2) for n, w, _ in loop],
        *[(n, w, 3) for n, w, _ in loop],
        ("roi_none", "item 9", 1),
    ]
    assert [(j.where, j.target, j.repeat) for j in plan.jumps] == [("item 8", 4, 2)]
    assert plan.end == "return_to_launch" and plan.pictures == 4
    assert [i.params[0] for i in plan.items if i.command in (93, 112)] == [2, 2, 2, 1]
    assert len(plan.fence.circles) == 1 and plan.fence.circles[0].inclusion
    assert len(plan.fence.polygons) == 1 and not plan.fence.polygons[0].inclusion
    assert [(r.latitude_deg, r.relative_altitude_m) for r in plan.rally_points] == [(47.39765, 15)]


def test_a_jump_repeats_its_loop_deterministically(tmp_path: Path) -> None:
    items = numbered(
        [TAKEOFF, WAYPOINT, SPLINE, simple(177, [2, 3, 0, 0, 0, 0, 0], 2), simple(20, [0] * 7, 2)]
    )
    plan = load_plan(plan_file(tmp_path, items))
    assert [(i.where, i.lap) for i in plan.waypoints] == [
        (f"item {k}", lap) for lap in (1, 2, 3, 4) for k in (1, 2)
    ]
    assert plan == load_plan(plan_file(tmp_path, items))  # the same list every time
    # A QGC WPL file's jump names the line's index.
    wpl = tmp_path / "loop.waypoints"
    wpl.write_text(
        "QGC WPL 110\n"
        "0 1 0 16 0 0 0 0 47.0 8.0 488 1\n"
        "1 0 3 22 0 0 0 0 47.0 8.0 10 1\n"
        "2 0 3 16 0 0 0 0 47.0001 8.0 10 1\n"
        "3 0 2 177 2 1 0 0 0 0 0 1\n"
    )
    looped = load_plan(str(wpl))
    assert [i.where for i in looped.waypoints] == ["item 2", "item 2"]
    assert looped.end == "hold" and "end=hold, the default" in looped.end_by


def test_nested_jumps_count_each_their_own(tmp_path: Path) -> None:
    inner = simple(177, [2, 1, 0, 0, 0, 0, 0], 2)  # item 2 twice each outer lap
    outer = simple(177, [2, 1, 0, 0, 0, 0, 0], 2)
    items = numbered([TAKEOFF, WAYPOINT, inner, SPLINE, outer])
    laps = [i.where for i in load_plan(plan_file(tmp_path, items)).waypoints]
    # As an autopilot counts them: the inner jump's count is spent on the first pass.
    assert laps == ["item 1", "item 1", "item 3", "item 1", "item 3"]


def test_the_missions_end_is_the_runs_choice_unless_the_plan_ends_itself(tmp_path: Path) -> None:
    open_ended = plan_file(tmp_path, [TAKEOFF, WAYPOINT])
    assert load_plan(open_ended).end == "hold"
    assert load_plan(open_ended, "land").end == "land"
    assert load_plan(open_ended, "rtl").end == "return_to_launch"
    ends_itself = load_plan(plan_file(tmp_path, [TAKEOFF, WAYPOINT, simple(21, [0] * 7, 2)]), "rtl")
    assert ends_itself.end == "land" and "end=rtl is not used" in ends_itself.notes[0]
    with pytest.raises(PlanError, match="end='park': the mission's end is one of land, rtl"):
        load_plan(open_ended, "park")


TERRAIN_WAYPOINT = {
    **simple(16, [0, 0, 0, None, 47.0001, 8.0, None], 0),
    "AltitudeMode": 3,
    "AMSLAltAboveTerrain": None,
}


@pytest.mark.parametrize(
    ("items", "message"),
    [
        (
            [TAKEOFF, simple(17, [0, 0, 0, 0, 47.0001, 8.0, 20])],
            "item 1: NAV_LOITER_UNLIM (17) loiters until someone moves the vehicle on, which a "
            "mission program never does: the plan would not end. Use NAV_LOITER_TIME (19)",
        ),
        (
            [TAKEOFF, TERRAIN_WAYPOINT],
            "item 1: NAV_WAYPOINT (16): AltitudeMode 3 (calculated above terrain) without an "
            "altitude: QGroundControl computes it from terrain data, and the plan was saved "
            "without them. Save the plan in QGroundControl with terrain data loaded",
        ),
        (
            [TAKEOFF, {**simple(16, [0, 0, 0, 0, 47.0001, 8.0, 20], 10), "AltitudeMode": 4}],
            "item 1: NAV_WAYPOINT (16): frame 10 (GLOBAL_TERRAIN_ALT, AltitudeMode 4 (terrain "
            "frame)) is above terrain, and the drone flies above home. In QGroundControl, set",
        ),
        (
            [TAKEOFF, simple(195, [0, 0, 0, 0, 47.0, 8.0, 5], 10)],
            "item 1: DO_SET_ROI_LOCATION (195): frame 10 (GLOBAL_TERRAIN_ALT) is above terrain",
        ),
        (
            [TAKEOFF, simple(201, [1, 0, 0, 0, 0, 0, 0], 2)],
            "item 1: DO_SET_ROI (201) with param1 (ROI mode) 1: only location (3) and none (0) "
            "are flown",
        ),
        (
            [TAKEOFF, simple(195, [0] * 7)],
            "item 1: DO_SET_ROI_LOCATION (195) has no location (latitude and longitude 0); "
            "place the region of interest on the map",
        ),
        (
            [TAKEOFF, WAYPOINT, simple(177, [2, -1, 0, 0, 0, 0, 0], 2)],
            "item 2: DO_JUMP (177): param2 (repeat count) is -1: a loop that repeats forever "
            "never ends the mission. Give the number of times to repeat",
        ),
        (
            numbered([TAKEOFF, WAYPOINT, simple(177, [9, 1, 0, 0, 0, 0, 0], 2)]),
            "item 2: DO_JUMP (177) to item number 9, which the plan does not have; pick the "
            "item to jump to in QGroundControl",
        ),
        (
            numbered([TAKEOFF, WAYPOINT, simple(177, [1, 1, 0, 0, 0, 0, 0], 2)]),
            "item 2: DO_JUMP (177) to item 0, a NAV_TAKEOFF (22): a loop cannot start there",
        ),
        (
            numbered([TAKEOFF, WAYPOINT, simple(177, [2, 20_000, 0, 0, 0, 0, 0], 2)]),
            "its DO_JUMP loops expand to more than 10000 items flown (item 2 x20000); lower",
        ),
        (
            [TAKEOFF, simple(93, [-1, 12, 30, 0, 0, 0, 0], 2)],
            "item 1: NAV_DELAY (93) waits until a time of day (param1 -1, hours, minutes, "
            "seconds in params 2-4): a replayed mission must wait the same",
        ),
        (
            [TAKEOFF, simple(112, [-5, 0, 0, 0, 0, 0, 0], 2)],
            "item 1: CONDITION_DELAY (112): param1 (delay) is -5 s; give the seconds to wait",
        ),
        (
            [TAKEOFF, simple(82, [0] * 7)],
            "item 1: NAV_SPLINE_WAYPOINT (82) has no position (latitude and longitude 0); "
            "place it on the map",
        ),
    ],
)
def test_each_refusal_names_the_item_the_command_the_reason_and_the_remedy(
    tmp_path: Path, items: list[dict[str, Any]], message: str
) -> None:
    with pytest.raises(PlanError) as refused:
        load_plan(plan_file(tmp_path, items))
    assert message in str(refused.value)


def test_a_terrain_item_saved_with_terrain_data_is_flown_at_its_amsl_altitude(
    tmp_path: Path,
) -> None:
    computed = {**simple(16, [0, 0, 0, None, 47.0001, 8.0, 530], 0), "AltitudeMode": 3}
    plan = load_plan(plan_file(tmp_path, [TAKEOFF, computed]))
    assert plan.waypoints[0].altitude_m == 530 and plan.waypoints[0].frame == 0


def test_regions_of_interest_set_and_clear_as_the_plan_says(tmp_path: Path) -> None:
    items = [
        TAKEOFF,
        simple(195, STRUCTURE),
        WAYPOINT,
        simple(201, [3, *STRUCTURE[1:]]),
        simple(201, [0] * 7, 2),
        SPLINE,
        simple(197, [0] * 7, 2),
    ]
    plan = load_plan(plan_file(tmp_path, items))
    assert [name for name, _ in plan.vehicle_steps] == [
        "roi",
        "goto",
        "roi",
        "roi_none",
        "goto",
        "roi_none",
    ]


def test_the_fence_and_rally_points_are_read_and_checked(tmp_path: Path) -> None:
    def with_safety(fence: Any, rally: Any) -> str:
        path = tmp_path / "safety.plan"
        document = {
            "fileType": "Plan",
            "mission": {"items": [TAKEOFF, WAYPOINT]},
            "geoFence": fence,
            "rallyPoints": rally,
        }
        path.write_text(json.dumps(document))
        return str(path)

    square = [[47.0, 8.0], [47.0, 8.001], [47.001, 8.001], [47.001, 8.0]]
    plan = load_plan(
        with_safety(
            {"polygons": [{"polygon": square, "inclusion": True}], "circles": [], "version": 2},
            {"points": [[47.0005, 8.0005, 20]], "version": 2},
        )
    )
    assert plan.fence.polygons[0].vertices[1] == (47.0, 8.001)
    assert plan.rally_points[0].relative_altitude_m == 20
    with pytest.raises(PlanError, match="geoFence polygon 0: a fence polygon needs at least 3"):
        load_plan(with_safety({"polygons": [{"polygon": square[:2]}]}, None))
    with pytest.raises(PlanError, match="geoFence circle 0: a fence circle needs a center"):
        load_plan(with_safety({"circles": [{"circle": {"center": [47, 8], "radius": 0}}]}, None))
    with pytest.raises(PlanError, match=r"rally point 0: 95, 8 is not a latitude in \[-90, 90\]"):
        load_plan(with_safety(None, {"points": [[95, 8, 10]]}))
    with pytest.raises(PlanError, match="rally point 0: no altitude"):
        load_plan(with_safety(None, {"points": [[47, 8]]}))


def test_the_check_prints_each_item_the_loops_the_end_and_the_safety_net(tmp_path: Path) -> None:
    def check(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "baton.missions.plan", *args],
            capture_output=True,
            text=True,
            timeout=60,
        )

    shown = check(str(EXAMPLES / "inspection.plan"))
    assert shown.returncode == 0, shown.stderr
    lines = shown.stdout.splitlines()
    assert (
        "item 3 (lap 2): NAV_SPLINE_WAYPOINT (82): fly to 47.3979000, 8.5459000 at 12 m above "
        "home (a spline waypoint, flown straight as a waypoint)"
    ) in lines
    assert (
        "item 2: DO_SET_ROI_LOCATION (195): point the camera at 47.3978200, 8.5457500, 2 m "
        "above home" in lines
    )
    assert "item 9: DO_SET_ROI_NONE (197): clear the region of interest" in lines
    assert "item 5 (lap 3): CONDITION_DELAY (112): wait 2 s" in lines
    assert (
        "item 8: DO_JUMP (177): back to item 3 (number 4) 2 time(s): its loop is flown 3 "
        "times, expanded above"
    ) in lines
    assert "then return to launch (its last item, item 12: NAV_RETURN_TO_LAUNCH (20))" in lines
    assert "geofence: inclusion circle of 150 m around 47.3977420, 8.5455940" in lines
    assert "rally point: 47.3976500, 8.5454000 at 15 m" in lines
    assert lines[-1] == "7 waypoints, 4 pictures"
    open_ended = plan_file(tmp_path, [TAKEOFF, WAYPOINT])
    assert "then land (end=land)" in check(open_ended, "end=land").stdout
    assert "then hold (end=hold, the default)" in check(open_ended).stdout
    refused = check(plan_file(tmp_path, [TAKEOFF, simple(17, [0] * 7, 2)]))
    assert refused.returncode == 1 and refused.stdout == ""
    assert refused.stderr.startswith("refused: plan ") and refused.stderr.endswith("end=hold\n")
    assert refused.stderr.count("\n") == 1
    assert check(open_ended, "end=land", "x").returncode == 2
