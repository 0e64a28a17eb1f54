"""The mission's geofence as a pure rule (sdk/fence.py, drone/fence.py): inside and outside, on the
edge, exclusion zones, the ceiling, the refusal of a Goto out of it, a breach, a fence
that cannot be flown, and the core's refusal path and failsafe (issue 32, item 3)."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path

import grpc
import pytest

from baton.config import ConfigError, parse_config
from baton.digest import request_digest
from baton.drone.core import DroneCore
from baton.drone.fence import breach, move_refusal
from baton.drone.safety import SafetyParams, fence_params
from baton.drone.sequencer import Sequencer
from baton.missions.plan import PlanError, load_plan
from baton.sdk.fence import Fence, FenceCircle, FencePolygon, outside_points, polygon_problem
from baton.sim_vehicle.fence_upload import Ack, FenceUpload, Request
from baton.testbed.local import local_config
from baton.testbed.plan_fence import with_plan_fence
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2

HOME = (47.397742, 8.545594)
# About 390 m north-south by 410 m east-west around the home.
SQUARE = ((47.396, 8.543), (47.3995, 8.543), (47.3995, 8.5485), (47.396, 8.5485))
GOTO = "/baton.v1.Mobility/Goto"
TAKEOFF = "/baton.v1.Mobility/Takeoff"


def fence(**kwargs: object) -> Fence:
    return Fence((FencePolygon(SQUARE),), ceiling_m=60.0, **kwargs)  # type: ignore[arg-type]


def test_inside_outside_and_on_the_edge_of_a_polygon() -> None:
    f = fence()
    assert f.outside(*HOME, 30.0) is None
    assert f.outside(47.3995, 8.545) is None  # on the north edge: inside
    assert f.outside(47.396, 8.543) is None  # a vertex
    why = f.outside(47.3996, 8.545)  # 11 m north of the edge
    assert why == "outside the inclusion polygon of 4 vertices"
    assert f.outside(47.3977, 8.5486) is not None  # east
    # A concave polygon: the notch is outside.
    notch = FencePolygon(((0.0, 0.0), (0.0, 0.01), (0.005, 0.005), (0.01, 0.01), (0.01, 0.0)))
    assert notch.contains(0.002, 0.005)
    assert notch.contains(0.0, 0.005)  # on an edge
    assert notch.contains(0.008, 0.0075)  # beside the notch
    assert not notch.contains(0.005, 0.008)  # in it


def test_exclusion_zones_circles_and_the_ceiling() -> None:
    no_fly = FencePolygon(
        ((47.3983, 8.5462), (47.3983, 8.5465), (47.3985, 8.5465), (47.3985, 8.5462)), False
    )
    f = Fence((FencePolygon(SQUARE), no_fly), (FenceCircle(*HOME, 150.0),), 40.0)
    assert f.outside(47.3984, 8.54635) == "inside the exclusion polygon of 4 vertices"
    # Inside the polygon but 160 m from the circle's centre: every inclusion area counts.
    north = HOME[0] + 160 / 111_195
    assert f.outside(north, HOME[1]) is not None and "circle of 150 m" in str(
        f.outside(north, HOME[1])
    )
    assert f.outside(*HOME, 40.0) is None
    assert f.outside(*HOME, 40.5) == "40.5 m above home is above the fence's ceiling of 40 m"
    assert Fence(ceiling_m=10.0).outside(0.1, 0.1, 5.0) is None  # a ceiling alone


def test_a_goto_out_of_the_fence_is_refused_out_of_range_naming_the_target() -> None:
    f = fence()
    out = api.GotoRequest(latitude_deg=47.41, longitude_deg=8.545, relative_altitude_m=20)
    refused = move_refusal("Mobility.Goto", out, f)
    assert refused is not None and refused.code is grpc.StatusCode.OUT_OF_RANGE
    assert refused.message == (
        "Mobility.Goto to (47.4100000, 8.5450000, 20 m) is outside the mission's fence "
        "(outside the inclusion polygon of 4 vertices); nothing was executed"
    )
    inside = api.GotoRequest(latitude_deg=HOME[0], longitude_deg=HOME[1], relative_altitude_m=20)
    assert move_refusal("Mobility.Goto", inside, f) is None
    assert move_refusal("Mobility.Goto", out, None) is None
    high = move_refusal("Mobility.Takeoff", api.TakeoffRequest(altitude_m=61), f)
    assert high is not None and "above its ceiling of 60 m" in high.message
    assert move_refusal("Mobility.Takeoff", api.TakeoffRequest(altitude_m=60), f) is None
    # No latitude: left to the execution, which refuses it INVALID_ARGUMENT.
    assert move_refusal("Mobility.Goto", api.GotoRequest(longitude_deg=1.0), f) is None


def test_a_breach_is_read_from_the_vehicle_s_position() -> None:
    f = fence()
    out = api.Position(latitude_deg=47.41, longitude_deg=8.545, relative_altitude_m=10)
    assert breach(f, out) == "outside the inclusion polygon of 4 vertices"
    assert breach(f, api.Position()) is None  # not known yet
    assert breach(None, out) is None
    high = api.Position(latitude_deg=HOME[0], longitude_deg=HOME[1], relative_altitude_m=70)
    assert breach(f, high) is not None


def drone(f: Fence) -> DroneCore:
    seq = Sequencer([0, 1], initial_master=0)
    return DroneCore(seq, 1.0, SafetyParams(fence=f))


def test_the_core_refuses_a_goto_out_of_the_fence_after_admission() -> None:
    """Admitted (its number used, so every replica's program sees the same outcome) and
    refused OUT_OF_RANGE before execution."""
    core = drone(fence())
    payload = api.GotoRequest(
        latitude_deg=47.41, longitude_deg=8.545, relative_altitude_m=20
    ).SerializeToString()
    call = drone_pb2.InvokeRequest(controller_id=0, epoch=1, reqnr=1, method=GOTO, payload=payload)
    admitted = core.admit(call, request_digest(GOTO, payload), 0.0)
    assert admitted.cached is None and admitted.refused is not None
    assert admitted.refused.code is grpc.StatusCode.OUT_OF_RANGE
    assert core.books(admitted.refused)
    high = api.TakeoffRequest(altitude_m=100).SerializeToString()
    refused = core.refusal(TAKEOFF, high)
    assert refused is not None and "ceiling" in refused.message


def test_a_breach_puts_the_vehicle_in_the_fence_s_failsafe_once_per_breach() -> None:
    core = drone(fence(action="land"))
    out = api.Position(latitude_deg=47.41, longitude_deg=8.545, relative_altitude_m=10)
    inside = api.Position(latitude_deg=HOME[0], longitude_deg=HOME[1], relative_altitude_m=10)
    assert core.fence_due(1.0, inside, True) is None
    assert core.fence_due(2.0, out, False) is None  # on the ground: none
    due = core.fence_due(2.0, out, True)
    assert due is not None and (due.cause, due.action) == ("fence", "land")
    assert (
        due.reason == "fence breach: the vehicle at (47.4100000, 8.5450000, 10.0 m) is outside the "
        "inclusion polygon of 4 vertices: land"
    )
    assert core.fence_due(2.0, out, True) == due  # asked twice (the lock's re-check): same
    core.enter_failsafe(due)
    assert core.fence_due(3.0, out, True) is None  # in failsafe
    core.resume_mission(4.0)
    assert core.fence_due(5.0, out, True) is None  # still out after the resume: not again
    assert core.fence_due(6.0, api.Position(), True) is None  # position unknown
    assert core.fence_due(7.0, inside, True) is None  # back inside ...
    assert core.fence_due(8.0, out, True) is not None  # ... and out again: a new breach


def test_what_a_fence_polygon_must_be() -> None:
    assert polygon_problem(SQUARE) is None
    assert polygon_problem([*SQUARE, SQUARE[0]]) is None  # closed as GeoJSON closes it
    assert "at least 3 distinct vertices, it has 2" in str(polygon_problem(SQUARE[:2]))
    assert "at least 3 distinct" in str(polygon_problem([SQUARE[0], SQUARE[1], SQUARE[0]]))
    bowtie = [SQUARE[0], SQUARE[2], SQUARE[1], SQUARE[3]]
    assert "intersects itself" in str(polygon_problem(bowtie))
    assert "no area" in str(polygon_problem([(0.0, 0.0), (0.0, 0.001), (0.0, 0.002)]))
    assert "not a place" in str(polygon_problem([(91.0, 0.0), (0.0, 1.0), (1.0, 1.0)]))
    assert "not a place" in str(polygon_problem([(math.nan, 0.0), (0.0, 1.0), (1.0, 1.0)]))
    assert "[latitude, longitude]" in str(polygon_problem([(1.0,), (0.0, 1.0), (1.0, 1.0)]))
    lines = outside_points(fence(), [("home", *HOME, None), ("item 3", 47.41, 8.545, 20.0)])
    assert lines == [
        "item 3 (47.4100000, 8.5450000) is outside the inclusion polygon of 4 vertices"
    ]


BASE = {"controllers": [{"id": 0, "address": "127.0.0.1:0"}]}


@pytest.mark.parametrize(
    ("fence_config", "expected"),
    [
        (
            {"polygon": [list(v) for v in SQUARE[:2]], "ceiling": 60},
            "t.yaml: safety.fence.polygons[0].vertices: a fence polygon needs at least 3 "
            "distinct vertices, it has 2; list the corners of the area in order",
        ),
        (
            {"polygon": [list(SQUARE[i]) for i in (0, 2, 1, 3)], "ceiling": 60},
            "t.yaml: safety.fence.polygons[0].vertices: edges 0-1 and 2-3 cross: the polygon "
            "intersects itself; list its vertices in order around the area",
        ),
        (
            {"polygon": [list(v) for v in SQUARE], "ceiling": 0},
            "t.yaml: safety.fence.ceiling: the ceiling is 0.0: give the metres above home the "
            "vehicle may fly up to, a number > 0 (e.g. 120, the open category's limit)",
        ),
        (
            {"polygon": [list(v) for v in SQUARE], "ceiling": math.nan},
            "t.yaml: safety.fence.ceiling: the ceiling is nan: give the metres above home",
        ),
        (
            {"polygon": [[47.5, 8.6], [47.51, 8.6], [47.51, 8.61]], "ceiling": 60},
            "t.yaml: (top level): safety.fence: the mission's start, drone.home (47.3977420, "
            "8.5455940), is outside the inclusion polygon of 3 vertices: the vehicle would "
            "take off in breach; draw the fence around the home, or fix drone.home",
        ),
        (
            {"polygon": [list(v) for v in SQUARE], "ceiling": 60, "action": "hold"},
            "t.yaml: safety.fence.action: Input should be 'rtl' or 'land'",
        ),
        (
            {"circles": [{"center": [95, 8], "radius": 10}], "ceiling": 60},
            "t.yaml: safety.fence.circles[0].center: center [95.0, 8.0] is not a place",
        ),
    ],
)
def test_a_fence_that_cannot_be_flown_is_refused_naming_file_field_and_fix(
    fence_config: dict[str, object], expected: str
) -> None:
    with pytest.raises(ConfigError) as refused:
        parse_config({**BASE, "safety": {"fence": fence_config}}, "t.yaml")
    assert str(refused.value).startswith(expected)


def test_a_configured_fence_is_the_drone_s() -> None:
    config = parse_config(
        {
            **BASE,
            "safety": {
                "fence": {
                    "polygon": [list(v) for v in (*SQUARE, SQUARE[0])],
                    "circles": [{"center": list(HOME), "radius": 150, "inclusion": True}],
                    "ceiling": 60,
                }
            },
        }
    )
    assert config.safety.fence is not None
    f = config.safety.fence.fence()
    assert f.polygons == (FencePolygon(SQUARE),)  # the closing vertex dropped
    assert f.circles == (FenceCircle(*HOME, 150.0),) and f.ceiling_m == 60.0
    assert f.action == "rtl"


def test_the_autopilot_s_own_fence_parameters() -> None:
    ardupilot = fence_params(True, fence(action="land"))
    assert [(p.name, p.value, p.bits) for p in ardupilot] == [
        ("FENCE_TYPE", 5, True),  # set over the autopilot's own bits
        ("FENCE_ALT_MAX", 60.0, False),
        ("FENCE_ACTION", 2, False),
        ("FENCE_ENABLE", 1, False),
    ]
    px4 = fence_params(False, fence())
    assert [(p.name, p.value) for p in px4] == [("GF_MAX_VER_DIST", 60.0), ("GF_ACTION", 3)]
    # A fence without a ceiling leaves the autopilot's ceiling alone: PX4's
    # GF_MAX_VER_DIST unwritten, ArduPilot's altitude bit and FENCE_ALT_MAX untouched.
    open_sky = Fence((FencePolygon(SQUARE),))
    assert [(p.name, p.value) for p in fence_params(False, open_sky)] == [("GF_ACTION", 3)]
    assert [(p.name, p.value, p.bits) for p in fence_params(True, open_sky)] == [
        ("FENCE_TYPE", 4, True),
        ("FENCE_ACTION", 1, False),
        ("FENCE_ENABLE", 1, False),
    ]


class _Item:
    """A MISSION_ITEM_INT as pymavlink decodes it (the fields the upload reads)."""

    def __init__(self, seq: int, command: int, param1: float, lat: float, lon: float) -> None:
        self.seq, self.command, self.param1 = seq, command, param1
        self.x, self.y = round(lat * 1e7), round(lon * 1e7)


def test_the_sim_vehicle_takes_a_fence_upload_item_by_item() -> None:
    """MISSION_COUNT, a request per item (a copy of the last taken again), the fence
    held only once the last arrived; an item out of order ends the upload."""
    from pymavlink.dialects.v20 import common as mavlink

    vertex = mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION
    circle = mavlink.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION
    upload = FenceUpload()
    assert upload.on_count(5) == Request(0)
    items = [_Item(k, vertex, 4, *v) for k, v in enumerate(SQUARE)] + [
        _Item(4, circle, 20.0, *HOME)
    ]
    assert upload.on_item(items[0]) == Request(1)
    assert upload.on_item(items[0]) == Request(1)  # a copy
    for k in (1, 2, 3):
        assert upload.on_item(items[k]) == Request(k + 1)
    done = upload.on_item(items[4])
    assert isinstance(done, Ack) and done.result == mavlink.MAV_MISSION_ACCEPTED
    assert done.fence == Fence((FencePolygon(SQUARE),), (FenceCircle(*HOME, 20.0, False),))
    assert upload.on_item(items[4]) is None  # late: ignored
    assert upload.on_count(5) == Request(0)
    assert upload.on_item(items[2]) == Ack(mavlink.MAV_MISSION_INVALID_SEQUENCE)
    # A polygon of fewer vertices than it says is refused whole.
    assert upload.on_count(2) == Request(0)
    upload.on_item(items[0])
    assert upload.on_item(items[1]) == Ack(mavlink.MAV_MISSION_INVALID_PARAM1)
    assert upload.on_clear() == Ack(mavlink.MAV_MISSION_ACCEPTED, cleared=True)


def write_plan(tmp_path: Path, waypoint: tuple[float, float], fence: Mapping[str, object]) -> Path:
    """A .plan: a takeoff and one waypoint (above home), with ``fence`` as its geoFence."""

    def item(command: int, lat: float, lon: float) -> dict[str, object]:
        return {
            "type": "SimpleItem",
            "command": command,
            "frame": 3,
            "params": [0, 0, 0, None, lat, lon, 10],
        }

    document = {
        "fileType": "Plan",
        "mission": {"items": [item(22, *HOME), item(16, *waypoint)]},
        "geoFence": {"version": 2, **fence},
    }
    path = tmp_path / "fenced.plan"
    path.write_text(json.dumps(document))
    return path


def test_a_plan_flies_in_its_geofence_and_a_waypoint_outside_refuses_the_run(
    tmp_path: Path,
) -> None:
    circle = {"circles": [{"circle": {"center": list(HOME), "radius": 150}, "inclusion": True}]}
    inside = write_plan(tmp_path, (HOME[0] + 0.001, HOME[1]), circle)
    config = with_plan_fence(local_config(2), inside)
    assert config.safety.fence is not None
    fence = config.safety.fence.fence()
    assert fence.circles == (FenceCircle(*HOME, 150.0),)
    assert fence.ceiling_m == config.safety.max_altitude
    outside = write_plan(tmp_path, (HOME[0] + 0.002, HOME[1]), circle)  # 222 m north
    with pytest.raises(ValueError) as refused:
        with_plan_fence(local_config(2), outside)
    assert str(refused.value) == (
        f"plan {outside}: 1 waypoint(s) outside the plan's geoFence: item 1 (47.3997420, "
        "8.5455940) is outside the inclusion circle of 150 m around (47.3977420, "
        "8.5455940). Nothing was flown: move the waypoints inside the fence, or redraw the "
        "fence"
    )


def test_a_plan_whose_fence_polygon_crosses_itself_is_refused(tmp_path: Path) -> None:
    bowtie = [list(SQUARE[i]) for i in (0, 2, 1, 3)]
    path = write_plan(tmp_path, HOME, {"polygons": [{"polygon": bowtie, "inclusion": True}]})
    with pytest.raises(PlanError) as refused:
        load_plan(str(path))
    assert "geoFence polygon 0: edges 0-1 and 2-3 cross: the polygon intersects itself" in str(
        refused.value
    )
