"""A mission's route for admission: the take-off point first, then the positions
flown to, in order, from a QGroundControl plan or a survey's waypoints."""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from pathlib import Path

from baton.missions.plan import WPL_HEADER, Plan, PlanError, load_plan
from baton.sdk.geo import offset
from baton.sdk.types import Position


def survey_route(home: Position, targets: Iterable[tuple[float, float]]) -> list[Position]:
    """The route of a survey flown from ``home`` to ``targets`` ((north, east) metres
    of take-off, in flying order)."""
    return [home, *(offset(home, north, east) for north, east in targets)]


def plan_route(plan: Plan, home: Position) -> list[Position]:
    """The route of a checked plan flown from ``home``: its waypoints (a loop's once a
    lap, the land position last)."""
    return [home, *(Position(w.latitude_deg, w.longitude_deg) for w in plan.waypoints)]


def planned_home(path: Path) -> Position | None:
    """Where the plan says the vehicle takes off: a ``.plan``'s
    ``mission.plannedHomePosition``, a ``QGC WPL`` file's item 0; None if it has none.
    The file is read as ``load_plan`` has checked it; PlanError if it cannot be."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise PlanError(f"plan {path}: cannot read it ({exc.strerror})") from None
    if text.lstrip().startswith(WPL_HEADER):
        for line in text.strip().splitlines()[1:]:
            fields = line.split()
            if len(fields) == 12 and fields[0] == "0":
                return Position(float(fields[8]), float(fields[9]))
        return None
    home = json.loads(text).get("mission", {}).get("plannedHomePosition")
    if isinstance(home, list) and len(home) >= 2 and all(isinstance(v, int | float) for v in home):
        return Position(float(home[0]), float(home[1]))
    return None


class RouteError(ValueError):
    """A submitted route that cannot be read: the field at fault (``route``, ``plan``,
    ``home``) and what is wrong with it, for a person."""

    def __init__(self, field: str, reason: str) -> None:
        super().__init__(f"{field}: {reason}")
        self.field = field
        self.reason = reason


def submitted_route(
    points: Sequence[Position], plan: Path | None, home: Position | None
) -> list[Position]:
    """The route a submission gives: its ``points`` (take-off first), or ``plan``'s
    waypoints flown from ``home`` (default: the plan's planned home position);
    RouteError naming the field."""
    if plan is None:
        if home is not None:
            raise RouteError("home", "only with a plan; a route's first point is its take-off")
        if not points:
            raise RouteError("route", "empty: give the take-off point first, or a plan")
        return list(points)
    if points:
        raise RouteError("route", "give a route or a plan, not both")
    try:
        loaded = load_plan(str(plan))
        take_off = home if home is not None else planned_home(plan)
    except PlanError as exc:
        raise RouteError("plan", str(exc)) from None
    if take_off is None:
        raise RouteError(
            "home",
            f"missing: plan {plan} has no planned home position; give the take-off point",
        )
    return plan_route(loaded, take_off)
