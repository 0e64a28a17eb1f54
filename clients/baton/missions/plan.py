"""Flies a QGroundControl plan: a ``.plan`` file, or the plain ``QGC WPL 110`` format.

    baton testbed --mission examples/survey.plan
    baton controller --mission .../baton/missions/plan.py --mission-arg plan=FILE [end=rtl]
    python -m baton.missions.plan FILE [end=land|rtl|hold]   # check a plan: what is flown

The plan is read and checked whole before the first drone call: an item we
do not fly is refused up front, naming the item, its command, why, and what
the author can do, and nothing is flown. Then: wait until the vehicle is
ready, arm, take off (to the plan's takeoff altitude, else the first
waypoint's), fly the items in order, and end as the plan ends (its last
NAV_LAND or NAV_RETURN_TO_LAUNCH) or, without one, as the run chose
(``end=land|rtl|hold``; default ``hold``, what PX4 and ArduPilot do after a
mission's last item). docs/plans.md is the author's guide.

The items flown (MAV_CMD numbers, https://mavlink.io/en/messages/common.html):

- ``NAV_TAKEOFF`` (22): the takeoff altitude; at most one, first.
- ``NAV_WAYPOINT`` (16): go to it, at its altitude, and hold ``param1``
  seconds; ``NAV_LOITER_TIME`` (19): go to it (or stay) for ``param1`` s;
  ``NAV_SPLINE_WAYPOINT`` (82): flown as a waypoint (straight there: the drone
  API's Goto flies straight lines).
- ``NAV_LAND`` (21) (at its position, if it has one), ``NAV_RETURN_TO_LAUNCH``
  (20): the plan's end.
- ``DO_CHANGE_SPEED`` (178): ``param2`` m/s from then on.
- ``DO_JUMP`` (177): back (or on) to the item numbered ``param1``,
  ``param2`` more times; expanded when the plan is read, so the items flown
  are one fixed list and a replay asks the same calls in the same order.
- ``CONDITION_DELAY`` (112), ``NAV_DELAY`` (93): wait ``param1`` seconds
  (the mission clock's Sleep, logged and replayed like any call).
- Regions of interest: ``DO_SET_ROI_LOCATION`` (195) and ``DO_SET_ROI`` (201)
  in location mode point the camera at a location (Gimbal.SetRoiLocation);
  ``DO_SET_ROI_NONE`` (197) and ``DO_SET_ROI`` mode none clear it.
- Camera: ``IMAGE_START_CAPTURE`` (2000) with ``param3`` images (not 0, which
  means "until stopped") ``param2`` s apart, ``DO_DIGICAM_CONTROL`` (203) with
  ``param5`` (shoot) 1: pictures where the vehicle is;
  ``DO_SET_CAM_TRIGG_DIST`` (206): a picture every ``param1`` metres flown
  from then on (0 stops it; ``param3`` 1: one at once), checked at each
  position poll. ``IMAGE_STOP_CAPTURE`` (2001), ``SET_CAMERA_MODE`` (530) and
  ``DO_SET_CAM_TRIGG_DIST`` 0 change nothing else.

Altitudes: frames ``GLOBAL_RELATIVE_ALT`` (3, 6) are above home; ``GLOBAL``
(0, 5) are above mean sea level, flown relative to the vehicle's home.
``MISSION`` (2) is for commands without a position. Terrain-relative items
(frames 10, 11; or QGroundControl's ``AltitudeMode`` 3 or 4 without an
altitude) are refused: the drone API flies above home. A ``QGC WPL`` file's
item 0 is the home position, as QGroundControl writes it, and is not flown.

A ``.plan``'s ``ComplexItem`` ``survey`` (also ``CorridorScan``) is flown as
QGroundControl would upload it: its ``TransectStyleComplexItem.Items``; a file
without them is expanded from its ``VisualTransectPoints`` (pairs: a transect's
entry and exit), at the survey's altitude, with a picture every frontal
footprint (``CameraCalc.AdjustedFootprintFrontal``) along each transect:
hovering at each with ``HoverAndCapture``, else by distance while flying.

A ``.plan``'s ``geoFence`` (inclusion and exclusion polygons and circles) and
``rallyPoints`` are read, checked and kept in the ``Plan`` (``fence``,
``rally_points``); they change nothing flown here. The testbed makes the fence the
mission's (the drone enforces it) when its configuration has none.
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from baton.missions.grid import wait_until_ready
from baton.sdk import Drone, Position, distance_m
from baton.sdk.fence import FenceCircle, FencePolygon, open_ring, polygon_problem

# Command numbers and names (MAV_CMD) of the items flown, and of others a plan
# may hold, so that a refusal names them.
NAV_WAYPOINT = 16
NAV_LOITER_UNLIM = 17
NAV_LOITER_TIME = 19
NAV_RETURN_TO_LAUNCH = 20
NAV_LAND = 21
NAV_TAKEOFF = 22
NAV_SPLINE_WAYPOINT = 82
NAV_DELAY = 93
CONDITION_DELAY = 112
DO_JUMP = 177
DO_CHANGE_SPEED = 178
DO_SET_ROI_LOCATION = 195
DO_SET_ROI_NONE = 197
DO_SET_ROI = 201
DO_DIGICAM_CONTROL = 203
DO_SET_CAM_TRIGG_DIST = 206
SET_CAMERA_MODE = 530
IMAGE_START_CAPTURE = 2000
IMAGE_STOP_CAPTURE = 2001
COMMAND_NAMES = {
    16: "NAV_WAYPOINT",
    17: "NAV_LOITER_UNLIM",
    18: "NAV_LOITER_TURNS",
    19: "NAV_LOITER_TIME",
    20: "NAV_RETURN_TO_LAUNCH",
    21: "NAV_LAND",
    22: "NAV_TAKEOFF",
    31: "NAV_LOITER_TO_ALT",
    82: "NAV_SPLINE_WAYPOINT",
    84: "NAV_VTOL_TAKEOFF",
    85: "NAV_VTOL_LAND",
    93: "NAV_DELAY",
    112: "CONDITION_DELAY",
    113: "CONDITION_CHANGE_ALT",
    114: "CONDITION_DISTANCE",
    115: "CONDITION_YAW",
    177: "DO_JUMP",
    178: "DO_CHANGE_SPEED",
    179: "DO_SET_HOME",
    181: "DO_SET_RELAY",
    183: "DO_SET_SERVO",
    189: "DO_LAND_START",
    195: "DO_SET_ROI_LOCATION",
    197: "DO_SET_ROI_NONE",
    201: "DO_SET_ROI",
    203: "DO_DIGICAM_CONTROL",
    205: "DO_MOUNT_CONTROL",
    206: "DO_SET_CAM_TRIGG_DIST",
    211: "DO_GRIPPER",
    214: "DO_SET_CAM_TRIGG_INTERVAL",
    530: "SET_CAMERA_MODE",
    1000: "DO_GIMBAL_MANAGER_PITCHYAW",
    2000: "IMAGE_START_CAPTURE",
    2001: "IMAGE_STOP_CAPTURE",
    2500: "VIDEO_START_CAPTURE",
    2501: "VIDEO_STOP_CAPTURE",
    3000: "DO_VTOL_TRANSITION",
}
# Every command flown, in the order the refusal lists them.
FLOWN = (
    NAV_WAYPOINT,
    NAV_LOITER_TIME,
    NAV_RETURN_TO_LAUNCH,
    NAV_LAND,
    NAV_TAKEOFF,
    NAV_SPLINE_WAYPOINT,
    NAV_DELAY,
    CONDITION_DELAY,
    DO_JUMP,
    DO_CHANGE_SPEED,
    DO_SET_ROI_LOCATION,
    DO_SET_ROI_NONE,
    DO_SET_ROI,
    DO_DIGICAM_CONTROL,
    DO_SET_CAM_TRIGG_DIST,
    SET_CAMERA_MODE,
    IMAGE_START_CAPTURE,
    IMAGE_STOP_CAPTURE,
)
# Items flown to a position (a spline as a straight waypoint).
WAYPOINTS = (NAV_WAYPOINT, NAV_LOITER_TIME, NAV_SPLINE_WAYPOINT)
NAVIGATES = (*WAYPOINTS, NAV_LAND, NAV_TAKEOFF)
WAITS = (CONDITION_DELAY, NAV_DELAY)
# DO_SET_ROI's param1 (MAV_ROI): the modes flown.
ROI_MODE_NONE, ROI_MODE_LOCATION = 0, 3
RELATIVE_FRAMES = (3, 6)  # GLOBAL_RELATIVE_ALT(_INT)
AMSL_FRAMES = (0, 5)  # GLOBAL(_INT)
TERRAIN_FRAMES = (10, 11)  # GLOBAL_TERRAIN_ALT(_INT)
MISSION_FRAME = 2
# QGroundControl's AltitudeMode of an item (its QML AltMode): the terrain ones.
ALTITUDE_MODES = {
    0: "mixed",
    1: "relative",
    2: "AMSL",
    3: "calculated above terrain",
    4: "terrain frame",
    5: "none",
}
TERRAIN_ALTITUDE_MODES = (3, 4)
WPL_HEADER = "QGC WPL 110"
# Hover-and-capture expansion of a survey without stored items: seconds to hold.
HOVER_S = 1.0
# What happens after the last item of a plan that does not end with NAV_LAND or
# NAV_RETURN_TO_LAUNCH: the run's choice (end=...), by default what PX4 and
# ArduPilot do at a mission's end (a multicopter holds at the last waypoint).
END_CHOICES = {"land": "land", "rtl": "return_to_launch", "hold": "hold"}
DEFAULT_END = "hold"
# DO_JUMP loops are expanded into the items flown; a plan that expands to more is
# refused (a loop that big is a mistake, or meant to run until stopped).
MAX_FLOWN_ITEMS = 10_000


class PlanError(ValueError):
    """A plan that cannot be flown, naming the file, the item, the reason and the fix."""


def command_name(command: int) -> str:
    """``NAV_WAYPOINT (16)``: a command as a person reads it."""
    return f"{COMMAND_NAMES.get(command, 'MAV_CMD')} ({command})"


@dataclass(frozen=True)
class Item:
    """One mission item: where it is in the file, its command, frame and seven params.

    ``seq``: its number in the mission as uploaded (QGroundControl's ``doJumpId``,
    a QGC WPL line's index), what a DO_JUMP names. ``altitude_mode``: a ``.plan``
    item's ``AltitudeMode``, if it has one. ``lap``: which time round a DO_JUMP loop
    this is (1 the first)."""

    where: str  # "item 3", "item 2 (survey), its item 5", "line 4"
    command: int
    frame: int
    params: tuple[float, ...]
    seq: int = 0
    altitude_mode: int | None = None
    lap: int = 1

    @property
    def latitude_deg(self) -> float:
        return self.params[4]

    @property
    def longitude_deg(self) -> float:
        return self.params[5]

    @property
    def altitude_m(self) -> float:
        return self.params[6]

    @property
    def has_position(self) -> bool:
        return not (self.latitude_deg == 0 and self.longitude_deg == 0)

    @property
    def sets_roi(self) -> bool:
        """Points the camera at this item's location."""
        return self.command == DO_SET_ROI_LOCATION or (
            self.command == DO_SET_ROI and self.params[0] == ROI_MODE_LOCATION
        )

    @property
    def clears_roi(self) -> bool:
        """Clears the region of interest."""
        return self.command == DO_SET_ROI_NONE or (
            self.command == DO_SET_ROI and self.params[0] == ROI_MODE_NONE
        )


@dataclass(frozen=True)
class Geofence:
    """A plan's geofence, as QGroundControl saved it (checked, not enforced here)."""

    polygons: tuple[FencePolygon, ...] = ()
    circles: tuple[FenceCircle, ...] = ()

    def __bool__(self) -> bool:
        return bool(self.polygons or self.circles)


@dataclass(frozen=True)
class RallyPoint:
    """A place a failsafe may land instead of home (altitude above home, metres)."""

    latitude_deg: float
    longitude_deg: float
    relative_altitude_m: float


@dataclass(frozen=True)
class Jump:
    """A DO_JUMP as the plan has it: to the item numbered ``target``, ``repeat`` times."""

    where: str
    target: int
    repeat: int
    target_where: str = ""


@dataclass
class Plan:
    """A checked plan: the takeoff altitude, the items flown after it (DO_JUMP loops
    expanded), how it ends, and the fence and rally points it carries."""

    path: Path
    takeoff_altitude_m: float
    items: list[Item]
    end: str  # "land", "return_to_launch" or "hold"
    land_at: Item | None = None
    cruise_speed_m_s: float | None = None  # the .plan's hoverSpeed
    notes: list[str] = field(default_factory=list)
    end_by: str = ""  # why it ends so: the plan's last item, or the run's choice
    jumps: list[Jump] = field(default_factory=list)
    fence: Geofence = field(default_factory=Geofence)
    rally_points: list[RallyPoint] = field(default_factory=list)

    @property
    def waypoints(self) -> list[Item]:
        """The positions flown to, in order (a loop's once a lap; the land position
        last, if any)."""
        flown = [i for i in self.items if i.command in WAYPOINTS and i.has_position]
        return [*flown, self.land_at] if self.land_at is not None else flown

    @property
    def vehicle_steps(self) -> list[tuple[str, Item]]:
        """What the vehicle is told, in order, as its effects name it: ``goto`` to each
        waypoint, ``roi`` and ``roi_none`` where the plan sets and clears the region
        of interest (the land position's goto last, if any)."""
        steps: list[tuple[str, Item]] = []
        for item in self.items:
            if item.command in WAYPOINTS and item.has_position:
                steps.append(("goto", item))
            elif item.sets_roi:
                steps.append(("roi", item))
            elif item.clears_roi:
                steps.append(("roi_none", item))
        return [*steps, ("goto", self.land_at)] if self.land_at is not None else steps

    @property
    def pictures(self) -> int | None:
        """Pictures the plan takes; None when some are taken by distance (it depends on
        where the position polls fall)."""
        total = 0
        for item in self.items:
            if item.command == DO_SET_CAM_TRIGG_DIST and item.params[0] > 0:
                return None
            total += _pictures_at(item)
        return total


def _pictures_at(item: Item) -> int:
    if item.command == IMAGE_START_CAPTURE:
        return int(item.params[2])
    if item.command == DO_DIGICAM_CONTROL and item.params[4] == 1:
        return 1
    return 0


def _number(value: Any, where: str, what: str) -> float:
    if value is None:
        return math.nan  # QGC writes NaN (e.g. an unset yaw) as null
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise PlanError(f"{where}: {what} is {value!r}, not a number")
    return float(value)


def _item(raw: Any, where: str, seq: int) -> Item:
    if not isinstance(raw, dict):
        raise PlanError(f"{where}: not a mission item object")
    params = raw.get("params")
    if not isinstance(params, list) or len(params) != 7:
        raise PlanError(f"{where}: 'params' must be a list of 7 numbers")
    command = raw.get("command")
    frame = raw.get("frame", MISSION_FRAME)
    if not isinstance(command, int) or not isinstance(frame, int):
        raise PlanError(f"{where}: 'command' and 'frame' must be integers")
    values = tuple(_number(p, where, f"param {k + 1}") for k, p in enumerate(params))
    jump_id = raw.get("doJumpId")
    mode = raw.get("AltitudeMode")
    return Item(
        where,
        command,
        frame,
        values,
        seq=jump_id if isinstance(jump_id, int) and not isinstance(jump_id, bool) else seq,
        altitude_mode=mode if isinstance(mode, int) and not isinstance(mode, bool) else None,
    )


@dataclass
class PlanFile:
    """What a plan file holds, read but not yet checked."""

    items: list[Item]
    hover_speed_m_s: float | None = None
    fence: Geofence = field(default_factory=Geofence)
    rally_points: list[RallyPoint] = field(default_factory=list)


def read_plan_file(path: Path) -> PlanFile:
    """The flat items of a ``.plan`` or ``QGC WPL`` file, its hover speed, fence and
    rally points."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise PlanError(f"plan {path}: cannot read it ({exc.strerror})") from None
    if text.lstrip().startswith("QGC WPL"):
        return PlanFile(_wpl_items(path, text))
    try:
        document = json.loads(text)
    except json.JSONDecodeError as exc:
        raise PlanError(
            f"plan {path}: neither a QGroundControl .plan (JSON: {exc}) nor a "
            f"'{WPL_HEADER}' waypoint file"
        ) from None
    if not isinstance(document, dict) or document.get("fileType") != "Plan":
        raise PlanError(f'plan {path}: a .plan file has "fileType": "Plan"')
    mission = document.get("mission")
    if not isinstance(mission, dict) or not isinstance(mission.get("items"), list):
        raise PlanError(f"plan {path}: no mission.items list")
    items: list[Item] = []
    for index, raw in enumerate(mission["items"]):
        where = f"item {index}"
        kind = raw.get("type") if isinstance(raw, dict) else None
        seq = items[-1].seq + 1 if items else 1  # home is 0 in the uploaded mission
        if kind == "SimpleItem":
            items.append(_item(raw, where, seq))
        elif kind == "ComplexItem":
            first = raw.get("doJumpId")
            start = first if isinstance(first, int) and not isinstance(first, bool) else seq
            items += _complex_items(raw, where, start)
        else:
            raise PlanError(f"plan {path}: {where}: type {kind!r}, not SimpleItem or ComplexItem")
    speed = mission.get("hoverSpeed")
    return PlanFile(
        items,
        float(speed) if isinstance(speed, int | float) and speed > 0 else None,
        _geofence(path, document.get("geoFence")),
        _rally_points(path, document.get("rallyPoints")),
    )


def read_plan_items(path: Path) -> tuple[list[Item], float | None]:
    """The flat items of a ``.plan`` or ``QGC WPL`` file, and the plan's hover speed."""
    plan_file = read_plan_file(path)
    return plan_file.items, plan_file.hover_speed_m_s


def _coordinate(path: Path, where: str, value: Any) -> tuple[float, float]:
    """A ``[lat, lon]`` of a fence or rally point, in range."""
    if (
        not isinstance(value, list | tuple)
        or len(value) < 2
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value[:2])
    ):
        raise PlanError(f"plan {path}: {where}: {value!r} is not [latitude, longitude]")
    lat, lon = float(value[0]), float(value[1])
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise PlanError(
            f"plan {path}: {where}: {lat:g}, {lon:g} is not a latitude in [-90, 90] and a "
            "longitude in [-180, 180]; fix the point in QGroundControl's fence or rally editor"
        )
    return lat, lon


def _geofence(path: Path, raw: Any) -> Geofence:
    """The ``geoFence`` of a .plan: its polygons and circles, checked."""
    if raw is None:
        return Geofence()
    if not isinstance(raw, dict):
        raise PlanError(f"plan {path}: geoFence is {raw!r}, not an object")
    polygons = []
    for k, polygon in enumerate(raw.get("polygons") or []):
        where = f"geoFence polygon {k}"
        vertices = polygon.get("polygon") if isinstance(polygon, dict) else None
        if not isinstance(vertices, list) or len(vertices) < 3:
            raise PlanError(
                f"plan {path}: {where}: a fence polygon needs at least 3 vertices "
                "([latitude, longitude] each); redraw it in QGroundControl's fence editor"
            )
        points = tuple(_coordinate(path, f"{where}, vertex {v}", p) for v, p in enumerate(vertices))
        problem = polygon_problem(points)
        if problem is not None:  # crossing edges, no area: the drone could not enforce it
            raise PlanError(
                f"plan {path}: {where}: {problem}; redraw it in QGroundControl's fence editor"
            )
        polygons.append(FencePolygon(open_ring(points), bool(polygon.get("inclusion", True))))
    circles = []
    for k, circle in enumerate(raw.get("circles") or []):
        where = f"geoFence circle {k}"
        shape = circle.get("circle") if isinstance(circle, dict) else None
        radius = shape.get("radius") if isinstance(shape, dict) else None
        if not isinstance(shape, dict) or not isinstance(radius, int | float) or not radius > 0:
            raise PlanError(
                f"plan {path}: {where}: a fence circle needs a center [latitude, longitude] "
                "and a radius > 0 m; redraw it in QGroundControl's fence editor"
            )
        lat, lon = _coordinate(path, f"{where}, center", shape.get("center"))
        circles.append(FenceCircle(lat, lon, float(radius), bool(circle.get("inclusion", True))))
    return Geofence(tuple(polygons), tuple(circles))


def _rally_points(path: Path, raw: Any) -> list[RallyPoint]:
    """The ``rallyPoints`` of a .plan: ``[latitude, longitude, altitude]`` each."""
    if raw is None:
        return []
    points = raw.get("points") if isinstance(raw, dict) else None
    if not isinstance(points, list):
        raise PlanError(f"plan {path}: rallyPoints has no 'points' list")
    rally = []
    for k, point in enumerate(points):
        where = f"rally point {k}"
        lat, lon = _coordinate(path, where, point)
        altitude = point[2] if len(point) > 2 else None
        if not isinstance(altitude, int | float) or not math.isfinite(altitude):
            raise PlanError(
                f"plan {path}: {where}: no altitude (a rally point is [latitude, longitude, "
                "altitude above home]); set its altitude in QGroundControl's rally editor"
            )
        rally.append(RallyPoint(lat, lon, float(altitude)))
    return rally


def _wpl_items(path: Path, text: str) -> list[Item]:
    lines = text.strip().splitlines()
    if lines[0].strip() != WPL_HEADER:
        raise PlanError(f"plan {path}: first line {lines[0].strip()!r}; expected '{WPL_HEADER}'")
    items = []
    for number, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        fields = line.split()
        if len(fields) != 12:
            raise PlanError(
                f"plan {path}: line {number}: {len(fields)} fields; a waypoint line has 12 "
                "(INDEX CURRENT FRAME COMMAND P1 P2 P3 P4 LAT LON ALT AUTOCONTINUE)"
            )
        try:
            index, frame, command = int(fields[0]), int(fields[2]), int(fields[3])
            params = tuple(float(v) for v in fields[4:11])
        except ValueError:
            raise PlanError(f"plan {path}: line {number}: not all numbers: {line!r}") from None
        if index == 0:
            continue  # the home position, as QGroundControl writes it
        items.append(Item(f"item {index}", command, frame, params, seq=index))
    return items


def _complex_items(raw: dict[str, Any], where: str, seq: int) -> list[Item]:
    kind = raw.get("complexItemType")
    if kind not in ("survey", "CorridorScan"):
        raise PlanError(
            f"{where}: complex item {kind!r} is not flown (a survey or a corridor scan is); "
            "remove it, or draw the same path as a survey or as waypoints"
        )
    where = f"{where} ({kind})"
    transect = raw.get("TransectStyleComplexItem")
    if not isinstance(transect, dict):
        raise PlanError(f"{where}: no TransectStyleComplexItem")
    stored = transect.get("Items")
    if isinstance(stored, list) and stored:
        return [
            _item({**inner, "doJumpId": None}, f"{where}, its item {k}", seq + k)
            if isinstance(inner, dict)
            else _item(inner, f"{where}, its item {k}", seq + k)
            for k, inner in enumerate(stored)
        ]
    expanded = _expand_transects(raw, transect, where)
    return [Item(i.where, i.command, i.frame, i.params, seq + k) for k, i in enumerate(expanded)]


def _expand_transects(raw: dict[str, Any], transect: dict[str, Any], where: str) -> list[Item]:
    """A survey's items from its visual transect points (QGC did not store them)."""
    points = transect.get("VisualTransectPoints")
    if not isinstance(points, list) or len(points) < 2 or len(points) % 2:
        raise PlanError(f"{where}: VisualTransectPoints must be entry/exit pairs of [lat, lon]")
    camera = transect.get("CameraCalc") or {}
    altitude = raw.get("Altitude", camera.get("DistanceToSurface"))
    spacing = camera.get("AdjustedFootprintFrontal")
    if not isinstance(altitude, int | float) or not isinstance(spacing, int | float):
        raise PlanError(
            f"{where}: without stored Items, a survey needs Altitude (or "
            "CameraCalc.DistanceToSurface) and CameraCalc.AdjustedFootprintFrontal"
        )
    if spacing <= 0:
        raise PlanError(f"{where}: CameraCalc.AdjustedFootprintFrontal must be > 0")
    hover = bool(transect.get("HoverAndCapture"))
    frame = RELATIVE_FRAMES[0]
    items: list[Item] = []

    def waypoint(lat: float, lon: float, hold: float, k: int) -> Item:
        return Item(f"{where}, point {k}", NAV_WAYPOINT, frame, (hold, 0, 0, 0, lat, lon, altitude))

    def camera_item(command: int, params: tuple[float, ...], k: int) -> Item:
        return Item(f"{where}, point {k}", command, MISSION_FRAME, params)

    for k in range(0, len(points), 2):
        try:
            (lat0, lon0), (lat1, lon1) = (
                (float(v) for v in points[k]),
                (float(v) for v in points[k + 1]),
            )
        except (TypeError, ValueError):
            raise PlanError(f"{where}: VisualTransectPoints {k}: not [lat, lon]") from None
        start = Position(lat0, lon0)
        length = distance_m(start, Position(lat1, lon1))
        if hover:
            shots = int(length // spacing) + 1
            for s in range(shots):
                f = s * spacing / length if length else 0.0
                lat, lon = lat0 + (lat1 - lat0) * f, lon0 + (lon1 - lon0) * f
                items.append(waypoint(lat, lon, HOVER_S, k))
                items.append(camera_item(IMAGE_START_CAPTURE, (0, 0, 1, 0, 0, 0, 0), k))
        else:
            items.append(waypoint(lat0, lon0, 0, k))
            items.append(camera_item(DO_SET_CAM_TRIGG_DIST, (spacing, 0, 1, 0, 0, 0, 0), k))
            items.append(waypoint(lat1, lon1, 0, k + 1))
            items.append(camera_item(DO_SET_CAM_TRIGG_DIST, (0, 0, 0, 0, 0, 0, 0), k + 1))
    return items


def _altitude_mode(item: Item) -> str:
    mode = item.altitude_mode
    return (
        f"AltitudeMode {mode} ({ALTITUDE_MODES.get(mode, 'unknown')})" if mode is not None else ""
    )


def _check(path: Path, item: Item) -> None:
    """Refuses an item we do not fly: the item, its command, why, and what to do."""
    refuse = f"plan {path}: {item.where}: {command_name(item.command)}"
    if item.command == NAV_LOITER_UNLIM:
        raise PlanError(
            f"{refuse} loiters until someone moves the vehicle on, which a mission program "
            "never does: the plan would not end. Use NAV_LOITER_TIME (19) with the seconds "
            "to stay, or end the plan there and run it with end=hold"
        )
    if item.command not in FLOWN:
        flown = ", ".join(command_name(c) for c in FLOWN)
        raise PlanError(
            f"{refuse} is not supported: the drone API has no call that does it. Remove it "
            f"from the plan; a plan may use {flown}"
        )
    positioned = item.command in NAVIGATES or item.sets_roi
    terrain_mode = item.altitude_mode in TERRAIN_ALTITUDE_MODES
    if positioned and item.has_position and item.frame in TERRAIN_FRAMES:
        mode = f", {_altitude_mode(item)}" if item.altitude_mode is not None else ""
        raise PlanError(
            f"{refuse}: frame {item.frame} (GLOBAL_TERRAIN_ALT{mode}) is above terrain, and "
            "the drone flies above home. In QGroundControl, set the item's altitude to "
            "'Calculated above terrain' and save the plan with terrain data loaded (its "
            "altitudes are then AMSL), or use relative altitudes"
        )
    if positioned and item.has_position and not math.isfinite(item.altitude_m) and terrain_mode:
        raise PlanError(
            f"{refuse}: {_altitude_mode(item)} without an altitude: QGroundControl computes "
            "it from terrain data, and the plan was saved without them. Save the plan in "
            "QGroundControl with terrain data loaded (params[6] then holds the AMSL "
            "altitude), or set the item's altitude mode to relative"
        )
    if positioned and item.has_position and item.frame not in RELATIVE_FRAMES + AMSL_FRAMES:
        raise PlanError(
            f"{refuse}: frame {item.frame} is not flown: altitudes are above home or above "
            "mean sea level. Use GLOBAL_RELATIVE_ALT (3) or GLOBAL (0)"
        )
    if positioned and item.has_position and not all(math.isfinite(p) for p in item.params[4:7]):
        raise PlanError(
            f"{refuse}: its latitude, longitude or altitude is missing (null); set its "
            "position and altitude in QGroundControl"
        )
    if item.command == IMAGE_START_CAPTURE and not item.params[2] >= 1:
        raise PlanError(
            f"{refuse} with param3 (total images) {item.params[2]:g}: capturing until stopped "
            "is not supported; give the number of images"
        )
    if item.command == DO_CHANGE_SPEED and not item.params[1] > 0:
        raise PlanError(f"{refuse}: param2 (speed) must be > 0 m/s; give the speed to fly")
    if item.command == NAV_WAYPOINT and not item.has_position:
        raise PlanError(f"{refuse} has no position (latitude and longitude 0); place it on the map")
    if item.command == NAV_SPLINE_WAYPOINT and not item.has_position:
        raise PlanError(f"{refuse} has no position (latitude and longitude 0); place it on the map")
    if item.command in WAITS:
        _check_wait(refuse, item)
    if item.command == DO_SET_ROI and not (item.sets_roi or item.clears_roi):
        raise PlanError(
            f"{refuse} with param1 (ROI mode) {item.params[0]:g}: only location (3) and none "
            "(0) are flown (the gimbal points at a place, or nowhere in particular). Use "
            "DO_SET_ROI_LOCATION (195) with the location to look at"
        )
    if item.sets_roi and not item.has_position:
        raise PlanError(
            f"{refuse} has no location (latitude and longitude 0); place the region of "
            "interest on the map"
        )
    if item.command == DO_JUMP:
        if not (item.params[0] >= 1 and float(item.params[0]).is_integer()):
            raise PlanError(
                f"{refuse}: param1 (the item to jump to) is {item.params[0]:g}, not an item "
                "number; pick the item to jump to in QGroundControl"
            )
        if not (item.params[1] >= 0 and float(item.params[1]).is_integer()):
            raise PlanError(
                f"{refuse}: param2 (repeat count) is {item.params[1]:g}: a loop that repeats "
                "forever never ends the mission. Give the number of times to repeat"
            )


def _check_wait(refuse: str, item: Item) -> None:
    seconds = item.params[0]
    if item.command == NAV_DELAY and seconds == -1:
        raise PlanError(
            f"{refuse} waits until a time of day (param1 -1, hours, minutes, seconds in "
            "params 2-4): a replayed mission must wait the same, so only a delay in seconds "
            "is flown. Give param1, the seconds to wait"
        )
    if not (math.isfinite(seconds) and seconds >= 0):
        raise PlanError(
            f"{refuse}: param1 (delay) is {seconds:g} s; give the seconds to wait (>= 0)"
        )


def expand_jumps(path: Path, items: list[Item]) -> tuple[list[Item], list[Jump]]:
    """The items flown, in order, with every DO_JUMP taken as many times as it says (as an
    autopilot does: each DO_JUMP counts its own jumps, from the plan's start), and the
    jumps themselves. Deterministic: the same plan is always the same list."""
    by_seq = {item.seq: k for k, item in enumerate(items)}
    jumps = []
    left: dict[int, int] = {}
    for k, item in enumerate(items):
        if item.command != DO_JUMP:
            continue
        target = int(item.params[0])
        if target not in by_seq:
            raise PlanError(
                f"plan {path}: {item.where}: DO_JUMP (177) to item number {target}, which the "
                "plan does not have; pick the item to jump to in QGroundControl"
            )
        if items[by_seq[target]].command in (NAV_TAKEOFF, DO_JUMP):
            raise PlanError(
                f"plan {path}: {item.where}: DO_JUMP (177) to {items[by_seq[target]].where}, a "
                f"{command_name(items[by_seq[target]].command)}: a loop cannot start there; "
                "jump to the first item of the loop after the takeoff"
            )
        jumps.append(Jump(item.where, target, int(item.params[1]), items[by_seq[target]].where))
        left[k] = int(item.params[1])
    laps: dict[int, int] = {}
    flown: list[Item] = []
    k = 0
    while k < len(items):
        item = items[k]
        if item.command == DO_JUMP:
            if left[k] > 0:
                left[k] -= 1
                k = by_seq[int(item.params[0])]
            else:
                k += 1
            continue
        laps[k] = laps.get(k, 0) + 1
        flown.append(replace(item, lap=laps[k]))
        if len(flown) > MAX_FLOWN_ITEMS:
            raise PlanError(
                f"plan {path}: its DO_JUMP loops expand to more than {MAX_FLOWN_ITEMS} items "
                f"flown ({', '.join(f'{j.where} x{j.repeat}' for j in jumps)}); lower their "
                "repeat counts"
            )
        k += 1
    return flown, jumps


def load_plan(path_text: str, end: str = "") -> Plan:
    """Reads and checks a plan; ``PlanError`` says what cannot be flown, before anything is.

    ``end``: what to do after the last item of a plan that does not end with NAV_LAND
    or NAV_RETURN_TO_LAUNCH (``land``, ``rtl`` or ``hold``; ``DEFAULT_END`` if not given).
    """
    if not path_text:
        raise PlanError("no plan given: pass plan=FILE (a QGroundControl .plan or QGC WPL file)")
    if end and end not in END_CHOICES:
        raise PlanError(f"end={end!r}: the mission's end is one of {', '.join(END_CHOICES)}")
    path = Path(path_text)
    plan_file = read_plan_file(path)
    for item in plan_file.items:
        _check(path, item)
    items, jumps = expand_jumps(path, plan_file.items)
    takeoffs = [k for k, item in enumerate(items) if item.command == NAV_TAKEOFF]
    misplaced = [k for k in takeoffs if k != 0]
    if misplaced:
        where = items[misplaced[0]].where
        raise PlanError(
            f"plan {path}: {where}: NAV_TAKEOFF (22) must be the plan's first item (and "
            "flown once); move it first, out of any DO_JUMP loop"
        )
    ends = [k for k, item in enumerate(items) if item.command in (NAV_LAND, NAV_RETURN_TO_LAUNCH)]
    if ends and ends != [len(items) - 1]:
        raise PlanError(
            f"plan {path}: {items[ends[0]].where}: {command_name(items[ends[0]].command)} "
            "must be the plan's last item (a plan ends there); move it last, out of any "
            "DO_JUMP loop"
        )
    first = takeoffs[0] + 1 if takeoffs else 0
    end_item = items[-1] if ends else None
    body = items[first : ends[0] if ends else len(items)]
    if not any(item.command in WAYPOINTS for item in body) and not takeoffs:
        raise PlanError(
            f"plan {path}: neither a takeoff nor a waypoint to fly; add a NAV_TAKEOFF (22)"
        )
    if takeoffs:
        altitude = items[0].altitude_m
    else:
        altitude = next(i.altitude_m for i in body if i.command in WAYPOINTS)
    if not altitude > 0:
        raise PlanError(
            f"plan {path}: the takeoff altitude must be > 0 m, got {altitude:g}; set the "
            "takeoff's altitude"
        )
    plan = Plan(
        path,
        altitude,
        body,
        END_CHOICES[end or DEFAULT_END],
        cruise_speed_m_s=plan_file.hover_speed_m_s,
        end_by=f"end={end}" if end else f"end={DEFAULT_END}, the default",
        jumps=jumps,
        fence=plan_file.fence,
        rally_points=plan_file.rally_points,
    )
    if end_item is not None:
        plan.end = "land" if end_item.command == NAV_LAND else "return_to_launch"
        plan.end_by = f"its last item, {end_item.where}: {command_name(end_item.command)}"
        if end:
            plan.notes.append(f"end={end} is not used: the plan ends with its own last item")
    if end_item is not None and end_item.command == NAV_LAND:
        plan.land_at = end_item if end_item.has_position else None
    return plan


def _relative(item: Item, home: Position) -> float:
    """The item's altitude above home."""
    if item.frame in AMSL_FRAMES:
        return item.altitude_m - home.absolute_altitude_m
    return item.altitude_m


class _Flight:
    """The plan being flown: the camera's distance trigger and the pictures taken."""

    def __init__(self, drone: Drone, poll_s: float, arrive_m: float) -> None:
        self.drone = drone
        self.poll_s = poll_s
        self.arrive_m = arrive_m
        self.trigger_m = 0.0
        self.last_shot: Position | None = None
        self.pictures = 0

    def picture(self) -> Position:
        picture = self.drone.camera.take_picture()
        self.pictures += 1
        print(
            f"picture {picture.sequence} at {picture.position.latitude_deg:.7f}, "
            f"{picture.position.longitude_deg:.7f}",
            flush=True,
        )
        return picture.position

    def fly_to(self, target: Position, altitude_m: float) -> None:
        """Goes to ``target`` at ``altitude_m`` above home; pictures by distance on the way."""
        self.drone.mobility.goto(target, relative_altitude_m=altitude_m)
        while True:
            here = self.drone.mobility.position()
            if self.trigger_m > 0 and (
                self.last_shot is None or distance_m(here, self.last_shot) >= self.trigger_m
            ):
                self.last_shot = self.picture()
            arrived = distance_m(here, target) <= self.arrive_m
            if arrived and abs(here.relative_altitude_m - altitude_m) <= 1.0:
                return
            self.drone.clock.sleep(self.poll_s)


def mission(
    drone: Drone,
    plan: str = "",
    speed_m_s: float = 0.0,
    poll_s: float = 1.0,
    arrive_m: float = 1.0,
    end: str = "",
) -> None:
    """Flies the plan file ``plan`` (speed: the plan's hover speed unless given, else 5 m/s;
    ``end``: land, rtl or hold after the last item, if the plan does not say)."""
    flight_plan = load_plan(plan, end)  # refused here, before anything is flown
    wait_until_ready(drone, poll_s)
    home = drone.mobility.home()
    drone.mobility.arm()
    drone.mobility.takeoff(flight_plan.takeoff_altitude_m)
    while drone.mobility.position().relative_altitude_m < flight_plan.takeoff_altitude_m - 0.5:
        drone.clock.sleep(poll_s)
    drone.mobility.set_speed(speed_m_s or flight_plan.cruise_speed_m_s or 5.0)
    flight = _Flight(drone, poll_s, arrive_m)
    altitude = flight_plan.takeoff_altitude_m
    for item in flight_plan.items:
        if item.command in WAYPOINTS:
            if item.has_position:
                altitude = _relative(item, home)
                target = Position(item.latitude_deg, item.longitude_deg)
                flight.fly_to(target, altitude)
                print(f"{item.where}: at {target.latitude_deg:.7f}, {target.longitude_deg:.7f}")
            hold = item.params[0]
            if hold > 0:
                drone.clock.sleep(hold)
        elif item.command in WAITS:
            drone.clock.sleep(item.params[0])
        elif item.sets_roi:
            roi = Position(item.latitude_deg, item.longitude_deg)
            drone.gimbal.set_roi_location(roi, relative_altitude_m=_relative(item, home))
        elif item.clears_roi:
            drone.gimbal.clear_roi()
        elif item.command == DO_CHANGE_SPEED:
            drone.mobility.set_speed(item.params[1])
        elif item.command == DO_SET_CAM_TRIGG_DIST:
            flight.trigger_m = item.params[0]
            flight.last_shot = flight.picture() if item.params[2] == 1 else None
        else:
            count = _pictures_at(item)
            for k in range(count):
                if k:
                    drone.clock.sleep(item.params[1])
                flight.picture()
    if flight_plan.end == "return_to_launch":
        drone.mobility.return_to_launch()
    elif flight_plan.end == "hold":
        drone.mobility.hold()  # as PX4 and ArduPilot do: hover at the last waypoint
        print(f"plan complete: {flight.pictures} pictures; holding", flush=True)
        return
    else:
        if flight_plan.land_at is not None:
            flight.trigger_m = 0.0
            land_at = flight_plan.land_at
            flight.fly_to(Position(land_at.latitude_deg, land_at.longitude_deg), altitude)
        drone.mobility.land()
    while drone.mobility.flight_state().in_air:
        drone.clock.sleep(poll_s)
    print(f"plan complete: {flight.pictures} pictures", flush=True)


def describe(item: Item) -> str:
    """What is flown for ``item``, in a few words (the plan check's line)."""
    c, p = item.command, item.params
    where = f"{item.latitude_deg:.7f}, {item.longitude_deg:.7f}"
    frame = "AMSL" if item.frame in AMSL_FRAMES else "above home"
    if c in WAYPOINTS and not item.has_position:
        return f"stay {p[0]:g} s where it is"
    if c in WAYPOINTS:
        text = f"fly to {where} at {item.altitude_m:g} m {frame}"
        if c == NAV_SPLINE_WAYPOINT:
            text += " (a spline waypoint, flown straight as a waypoint)"
        return text + (f", hold {p[0]:g} s" if p[0] > 0 else "")
    if c in WAITS:
        return f"wait {p[0]:g} s"
    if item.sets_roi:
        return f"point the camera at {where}, {item.altitude_m:g} m {frame}"
    if item.clears_roi:
        return "clear the region of interest"
    if c == DO_CHANGE_SPEED:
        return f"speed {p[1]:g} m/s"
    if c == DO_SET_CAM_TRIGG_DIST:
        return f"a picture every {p[0]:g} m" if p[0] > 0 else "stop pictures by distance"
    if _pictures_at(item):
        return f"{_pictures_at(item)} picture(s)"
    return "nothing (no effect on the flight)"


def check_lines(plan: Plan) -> list[str]:
    """The plan check's report: each item flown, the loops, the end, the fence, the rally
    points, and the totals."""
    lines = [f"take off to {plan.takeoff_altitude_m:g} m"]
    for item in plan.items:
        lap = f" (lap {item.lap})" if item.lap > 1 else ""
        lines.append(f"{item.where}{lap}: {command_name(item.command)}: {describe(item)}")
    for jump in plan.jumps:
        lines.append(
            f"{jump.where}: DO_JUMP (177): back to {jump.target_where} (number {jump.target}) "
            f"{jump.repeat} time(s): its loop is flown {jump.repeat + 1} times, expanded above"
        )
    if plan.land_at is not None:
        lines.append(f"then fly to {plan.land_at.where} and land")
    lines.append(f"then {plan.end.replace('_', ' ')} ({plan.end_by})")
    lines += plan.notes
    for polygon in plan.fence.polygons:
        kind = "inclusion" if polygon.inclusion else "exclusion"
        lines.append(f"geofence: {kind} polygon of {len(polygon.vertices)} vertices")
    for circle in plan.fence.circles:
        kind = "inclusion" if circle.inclusion else "exclusion"
        lines.append(
            f"geofence: {kind} circle of {circle.radius_m:g} m around "
            f"{circle.latitude_deg:.7f}, {circle.longitude_deg:.7f}"
        )
    for point in plan.rally_points:
        lines.append(
            f"rally point: {point.latitude_deg:.7f}, {point.longitude_deg:.7f} at "
            f"{point.relative_altitude_m:g} m"
        )
    if plan.fence or plan.rally_points:
        lines.append(
            "(the geofence is the testbed's fence when it has none: docs/plans.md; "
            "rally points are not used yet)"
        )
    pictures = plan.pictures
    lines.append(
        f"{len(plan.waypoints)} waypoints, "
        f"{'pictures by distance' if pictures is None else f'{pictures} pictures'}"
    )
    return lines


def main(argv: list[str] | None = None) -> int:
    """``python -m baton.missions.plan FILE [end=land|rtl|hold]``: checks a plan and prints
    what would be flown, or why it is refused (one line each, each ending its line)."""
    args = sys.argv[1:] if argv is None else argv
    ends = [a.partition("=")[2] for a in args[1:] if a.startswith("end=")]
    if not args or len(args) != 1 + len(ends) or len(ends) > 1:
        print("usage: python -m baton.missions.plan FILE [end=land|rtl|hold]", file=sys.stderr)
        return 2
    try:
        plan = load_plan(args[0], ends[0] if ends else "")
    except PlanError as exc:
        sys.stderr.write(f"refused: {str(exc).rstrip()}\n")
        return 1
    sys.stdout.write("".join(f"{line}\n" for line in check_lines(plan)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
