"""Flies a QGroundControl plan: a ``.plan`` file, or the plain ``QGC WPL 110`` format.

    baton testbed --mission examples/survey.plan
    baton controller --mission .../baton/missions/plan.py --mission-arg plan=FILE
    python -m baton.missions.plan FILE      # check a plan: its steps, or what is refused

The plan is read and checked whole before the first drone call: an item we
do not fly is refused up front with its index and command name, and nothing
is flown. Then: wait until the vehicle is ready, arm, take off (to the plan's
takeoff altitude, else the first waypoint's), fly the items in order, and
land or return to launch as the plan ends (land where it is if it does
neither).

The items flown (MAV_CMD numbers, https://mavlink.io/en/messages/common.html):

- ``NAV_TAKEOFF`` (22): the takeoff altitude; at most one, first.
- ``NAV_WAYPOINT`` (16): go to it, at its altitude, and hold ``param1``
  seconds; ``NAV_LOITER_TIME`` (19): go to it (or stay) for ``param1`` s.
- ``NAV_LAND`` (21) (at its position, if it has one), ``NAV_RETURN_TO_LAUNCH``
  (20): the plan's end.
- ``DO_CHANGE_SPEED`` (178): ``param2`` m/s from then on.
- Camera: ``IMAGE_START_CAPTURE`` (2000) with ``param3`` images (not 0, which
  means "until stopped") ``param2`` s apart, ``DO_DIGICAM_CONTROL`` (203) with
  ``param5`` (shoot) 1: pictures where the vehicle is;
  ``DO_SET_CAM_TRIGG_DIST`` (206): a picture every ``param1`` metres flown
  from then on (0 stops it; ``param3`` 1: one at once), checked at each
  position poll. ``IMAGE_STOP_CAPTURE`` (2001), ``SET_CAMERA_MODE`` (530) and
  ``DO_SET_CAM_TRIGG_DIST`` 0 change nothing else.

Altitudes: frames ``GLOBAL_RELATIVE_ALT`` (3, 6) are above home; ``GLOBAL``
(0, 5) are above mean sea level, flown relative to the vehicle's home.
``MISSION`` (2) is for commands without a position. A ``QGC WPL`` file's item
0 is the home position, as QGroundControl writes it, and is not flown.

A ``.plan``'s ``ComplexItem`` ``survey`` (also ``CorridorScan``) is flown as
QGroundControl would upload it: its ``TransectStyleComplexItem.Items``; a file
without them is expanded from its ``VisualTransectPoints`` (pairs: a transect's
entry and exit), at the survey's altitude, with a picture every frontal
footprint (``CameraCalc.AdjustedFootprintFrontal``) along each transect:
hovering at each with ``HoverAndCapture``, else by distance while flying.
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from baton.missions.grid import wait_until_ready
from baton.sdk import Drone, Position, distance_m

# Command numbers and names (MAV_CMD) of the items flown, and of others a plan
# may hold, so that a refusal names them.
NAV_WAYPOINT = 16
NAV_LOITER_TIME = 19
NAV_RETURN_TO_LAUNCH = 20
NAV_LAND = 21
NAV_TAKEOFF = 22
DO_CHANGE_SPEED = 178
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
RELATIVE_FRAMES = (3, 6)  # GLOBAL_RELATIVE_ALT(_INT)
AMSL_FRAMES = (0, 5)  # GLOBAL(_INT)
MISSION_FRAME = 2
WPL_HEADER = "QGC WPL 110"
# Hover-and-capture expansion of a survey without stored items: seconds to hold.
HOVER_S = 1.0


class PlanError(ValueError):
    """A plan that cannot be flown, naming the file, the item and the fix."""


def command_name(command: int) -> str:
    """``NAV_WAYPOINT (16)``: a command as a person reads it."""
    return f"{COMMAND_NAMES.get(command, 'MAV_CMD')} ({command})"


@dataclass(frozen=True)
class Item:
    """One mission item: where it is in the file, its command, frame and seven params."""

    where: str  # "item 3", "item 2 (survey), its item 5", "line 4"
    command: int
    frame: int
    params: tuple[float, ...]

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


@dataclass
class Plan:
    """A checked plan: the takeoff altitude, the items after it, how it ends."""

    path: Path
    takeoff_altitude_m: float
    items: list[Item]
    end: str  # "land", "return_to_launch" or "" (land where it is)
    land_at: Item | None = None
    cruise_speed_m_s: float | None = None  # the .plan's hoverSpeed
    notes: list[str] = field(default_factory=list)

    @property
    def waypoints(self) -> list[Item]:
        """The positions flown to, in order (the land position last, if any)."""
        flown = [i for i in self.items if i.command in (NAV_WAYPOINT, NAV_LOITER_TIME)]
        flown = [i for i in flown if i.has_position]
        return [*flown, self.land_at] if self.land_at is not None else flown

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


def _item(raw: Any, where: str) -> Item:
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
    return Item(where, command, frame, values)


def read_plan_items(path: Path) -> tuple[list[Item], float | None]:
    """The flat items of a ``.plan`` or ``QGC WPL`` file, and the plan's hover speed."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise PlanError(f"plan {path}: cannot read it ({exc.strerror})") from None
    if text.lstrip().startswith("QGC WPL"):
        return _wpl_items(path, text), None
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
        if kind == "SimpleItem":
            items.append(_item(raw, where))
        elif kind == "ComplexItem":
            items += _complex_items(raw, where)
        else:
            raise PlanError(f"plan {path}: {where}: type {kind!r}, not SimpleItem or ComplexItem")
    speed = mission.get("hoverSpeed")
    return items, float(speed) if isinstance(speed, int | float) and speed > 0 else None


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
        items.append(Item(f"item {index}", command, frame, params))
    return items


def _complex_items(raw: dict[str, Any], where: str) -> list[Item]:
    kind = raw.get("complexItemType")
    if kind not in ("survey", "CorridorScan"):
        raise PlanError(
            f"{where}: complex item {kind!r} is not flown (a survey or a corridor scan is)"
        )
    where = f"{where} ({kind})"
    transect = raw.get("TransectStyleComplexItem")
    if not isinstance(transect, dict):
        raise PlanError(f"{where}: no TransectStyleComplexItem")
    stored = transect.get("Items")
    if isinstance(stored, list) and stored:
        return [_item(inner, f"{where}, its item {k}") for k, inner in enumerate(stored)]
    return _expand_transects(raw, transect, where)


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


def _check(path: Path, item: Item) -> None:
    """Refuses an item we do not fly, naming it."""
    refuse = f"plan {path}: {item.where}: {command_name(item.command)}"
    navigates = item.command in (NAV_WAYPOINT, NAV_LOITER_TIME, NAV_LAND, NAV_TAKEOFF)
    if item.command not in (
        NAV_WAYPOINT,
        NAV_LOITER_TIME,
        NAV_RETURN_TO_LAUNCH,
        NAV_LAND,
        NAV_TAKEOFF,
        DO_CHANGE_SPEED,
        DO_DIGICAM_CONTROL,
        DO_SET_CAM_TRIGG_DIST,
        SET_CAMERA_MODE,
        IMAGE_START_CAPTURE,
        IMAGE_STOP_CAPTURE,
    ):
        flown = ", ".join(
            command_name(c)
            for c in (16, 19, 20, 21, 22, 178, 203, 206, 530, 2000, 2001)  # the list above
        )
        raise PlanError(f"{refuse} is not supported; a plan may use {flown}")
    if navigates and item.has_position and item.frame not in RELATIVE_FRAMES + AMSL_FRAMES:
        raise PlanError(
            f"{refuse}: frame {item.frame} is not flown; use GLOBAL_RELATIVE_ALT (3) or GLOBAL (0)"
        )
    if navigates and not all(math.isfinite(p) for p in item.params[4:7]) and item.has_position:
        raise PlanError(f"{refuse}: its position is not finite")
    if item.command == IMAGE_START_CAPTURE and not item.params[2] >= 1:
        raise PlanError(
            f"{refuse} with param3 (total images) {item.params[2]:g}: capturing until stopped "
            "is not supported; give the number of images"
        )
    if item.command == DO_CHANGE_SPEED and not item.params[1] > 0:
        raise PlanError(f"{refuse}: param2 (speed) must be > 0 m/s")
    if item.command in (NAV_WAYPOINT, NAV_LOITER_TIME) and not item.has_position:
        if item.command == NAV_WAYPOINT:
            raise PlanError(f"{refuse} has no position (latitude and longitude 0)")


def load_plan(path_text: str) -> Plan:
    """Reads and checks a plan; ``PlanError`` says what cannot be flown, before anything is."""
    if not path_text:
        raise PlanError("no plan given: pass plan=FILE (a QGroundControl .plan or QGC WPL file)")
    path = Path(path_text)
    items, speed = read_plan_items(path)
    for item in items:
        _check(path, item)
    takeoffs = [k for k, item in enumerate(items) if item.command == NAV_TAKEOFF]
    misplaced = [k for k in takeoffs if k != 0]
    if misplaced:
        where = items[misplaced[0]].where
        raise PlanError(f"plan {path}: {where}: NAV_TAKEOFF (22) must be the plan's first item")
    ends = [k for k, item in enumerate(items) if item.command in (NAV_LAND, NAV_RETURN_TO_LAUNCH)]
    if ends and ends != [len(items) - 1]:
        raise PlanError(
            f"plan {path}: {items[ends[0]].where}: {command_name(items[ends[0]].command)} "
            "must be the plan's last item (a plan ends there)"
        )
    first = takeoffs[0] + 1 if takeoffs else 0
    end_item = items[-1] if ends else None
    body = items[first : ends[0] if ends else len(items)]
    if not any(item.command == NAV_WAYPOINT for item in body) and not takeoffs:
        raise PlanError(f"plan {path}: neither a takeoff nor a waypoint to fly")
    if takeoffs:
        altitude = items[0].altitude_m
    else:
        altitude = next(i.altitude_m for i in body if i.command == NAV_WAYPOINT)
    if not altitude > 0:
        raise PlanError(f"plan {path}: the takeoff altitude must be > 0 m, got {altitude:g}")
    plan = Plan(path, altitude, body, "", cruise_speed_m_s=speed)
    if end_item is not None and end_item.command == NAV_LAND:
        plan.end = "land"
        plan.land_at = end_item if end_item.has_position else None
    elif end_item is not None:
        plan.end = "return_to_launch"
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
) -> None:
    """Flies the plan file ``plan`` (speed: the plan's hover speed unless given, else 5 m/s)."""
    flight_plan = load_plan(plan)  # refused here, before anything is flown
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
        if item.command in (NAV_WAYPOINT, NAV_LOITER_TIME):
            if item.has_position:
                altitude = _relative(item, home)
                target = Position(item.latitude_deg, item.longitude_deg)
                flight.fly_to(target, altitude)
                print(f"{item.where}: at {target.latitude_deg:.7f}, {target.longitude_deg:.7f}")
            hold = item.params[0]
            if hold > 0:
                drone.clock.sleep(hold)
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
    else:
        if flight_plan.land_at is not None:
            flight.trigger_m = 0.0
            land_at = flight_plan.land_at
            flight.fly_to(Position(land_at.latitude_deg, land_at.longitude_deg), altitude)
        drone.mobility.land()
    while drone.mobility.flight_state().in_air:
        drone.clock.sleep(poll_s)
    print(f"plan complete: {flight.pictures} pictures", flush=True)


def main(argv: list[str] | None = None) -> int:
    """``python -m baton.missions.plan FILE``: checks a plan and prints what would be flown."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m baton.missions.plan FILE", file=sys.stderr)
        return 2
    try:
        plan = load_plan(args[0])
    except PlanError as exc:
        print(f"refused: {exc}", file=sys.stderr)
        return 1
    print(f"take off to {plan.takeoff_altitude_m:g} m")
    for item in plan.items:
        print(f"{item.where}: {command_name(item.command)} {list(item.params)}")
    print(f"then {plan.end.replace('_', ' ') or 'land where it is'}")
    pictures = plan.pictures
    print(
        f"{len(plan.waypoints)} waypoints, "
        f"{'pictures by distance' if pictures is None else f'{pictures} pictures'}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
