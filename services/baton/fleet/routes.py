"""A mission's route for admission: the take-off point first, then the positions
flown to, in order, from a QGroundControl plan or a survey's waypoints."""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

from baton.missions.plan import WPL_HEADER, Plan, PlanError
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
