"""The fence a QGroundControl plan flies with: the testbed's ``safety.fence`` if it has
one, else the plan's own ``geoFence`` (its polygons and circles, inclusion and
exclusion, under the testbed's ``safety.max_altitude``); and the plan checked against
it before anything flies: every waypoint inside, or the run is refused naming the
items outside (docs/plans.md, "Geofence and rally points")."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from baton.config import BatonConfig
from baton.missions.plan import AMSL_FRAMES, Plan, load_plan
from baton.sdk.fence import outside_points


def plan_fence_document(plan: Plan, config: BatonConfig) -> dict[str, Any] | None:
    """The plan's ``geoFence`` as the testbed file's ``safety.fence``; None without one."""
    fence = plan.fence
    if not fence:
        return None
    return {
        "polygons": [
            {"vertices": [list(v) for v in p.vertices], "inclusion": p.inclusion}
            for p in fence.polygons
        ],
        "circles": [
            {
                "center": [c.latitude_deg, c.longitude_deg],
                "radius": c.radius_m,
                "inclusion": c.inclusion,
            }
            for c in fence.circles
        ],
        "ceiling": config.safety.max_altitude,
    }


def with_plan_fence(config: BatonConfig, plan_path: Path) -> BatonConfig:
    """``config`` flying the plan at ``plan_path``: its fence, the plan's when it has
    none; ValueError naming the file, each waypoint outside the fence and the fix."""
    plan = load_plan(str(plan_path))
    fence_config = config.safety.fence
    source = "the testbed's safety.fence"
    if fence_config is None:
        document = plan_fence_document(plan, config)
        if document is None:
            return config
        safety = config.model_dump(exclude_unset=True).get("safety", {})
        config = BatonConfig.model_validate(
            {**config.model_dump(exclude_unset=True), "safety": {**safety, "fence": document}}
        )
        fence_config = config.safety.fence
        source = "the plan's geoFence"
    assert fence_config is not None
    home = config.drone.home
    points = []
    for item in plan.waypoints:
        amsl = item.frame in AMSL_FRAMES
        relative = item.altitude_m - home.altitude_m if amsl else item.altitude_m
        points.append((item.where, item.latitude_deg, item.longitude_deg, relative))
    outside = outside_points(fence_config.fence(), points)
    if outside:
        raise ValueError(
            f"plan {plan_path}: {len(outside)} waypoint(s) outside {source}: "
            + "; ".join(outside)
            + ". Nothing was flown: move the waypoints inside the fence, or redraw the fence"
        )
    return config
