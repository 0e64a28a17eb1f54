"""Whole missions on the local testbed: small grids, a fast link, the paper's promises."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from typing import Any

from waiting import eventually

from baton.config import LinkSpec
from baton.testbed.local import (
    LocalTestbed,
    MissionPlan,
    Snapshot,
    TestbedPlan,
    local_config,
)
from baton.testbed.report import NOT_COUNTED, check_side_effects, resent_gotos
from baton.v1 import drone_pb2, ring_pb2

SMALL_GRID = MissionPlan(grid=2, spacing_m=20.0, altitude_m=5.0, speed_m_s=5.0, poll_s=1.0)


FAST_LINK = LinkSpec(latency=0.002, bandwidth=None)


def assert_exactly_once(snapshot: Snapshot) -> None:
    """Any mission's promises: every controller's program ended DONE, every request
    number executed once, and every replica's program saw the same replies."""
    drone = snapshot.drone
    for cid, c in snapshot.controllers.items():
        assert c.mission == ring_pb2.MISSION_STATE_DONE, (
            f"controller {cid}: mission {c.mission}: {c.mission_error}"
        )
    # Every request number executed exactly once, in order; every drone call
    # the replicas' programs made is in the audit (Clock calls are logged by
    # the controllers and never reach the drone, hence gaps in the numbers).
    executed = [a.reqnr for a in drone.audit]
    assert executed == sorted(set(executed))
    assert drone.executed == len(executed)
    assert {c.drone_calls for c in snapshot.controllers.values()} == {len(executed)}
    # Every replica's program saw the same replies, and as many as the drone served.
    chains = Counter(c.reply_chain for c in snapshot.controllers.values())
    assert len(chains) == 1, f"replicas diverged: {chains}"
    assert len({c.reqnr for c in snapshot.controllers.values()}) == 1


def assert_mission_promises(snapshot: Snapshot, plan: TestbedPlan) -> None:
    assert_exactly_once(snapshot)
    drone = snapshot.drone
    waypoints = plan.mission.grid**2
    # Every waypoint photographed once.
    assert snapshot.pictures == waypoints
    # The same, counted where it happened: one picture per waypoint produced
    # by the camera; one arm, takeoff and land, and each goto once and in the
    # grid's order, acted on by the sim vehicle (SITL or an autopilot of its
    # own counts nothing).
    effects = check_side_effects(snapshot, plan.mission.grid, plan.mission.spacing_m)
    assert effects["exactly_once"] is True, effects
    assert effects["pictures_taken"] == waypoints, effects
    if plan.vehicle == "sim":
        gotos = waypoints + resent_gotos(snapshot)  # a resume flies the last leg on
        assert effects["vehicle_commands"]["goto"] == gotos, effects
    else:
        assert effects["vehicle_commands"] == NOT_COUNTED, effects
    # Every scripted handover happened after the right request, and ended.
    # (A scripted reqnr that was a Clock call fires after the next drone request.)
    scripted = [h for h in drone.handovers if h.trigger == drone_pb2.HANDOVER_TRIGGER_SCRIPT]
    assert [h.new_master for h in scripted] == [mid for _, mid in plan.handovers], [
        (h.after_reqnr, h.old_master, h.new_master, h.trigger, h.kind, h.reason)
        for h in drone.handovers
    ]
    for record, (planned, _) in zip(scripted, plan.handovers, strict=True):
        # A prepared handover moves the master once the target caught up, later.
        assert planned <= record.after_reqnr <= planned + (1000 if plan.prepared else 2)
    # Every handover ended with the new master's first request, except one whose old
    # master's log never left (it died, or it was out of reach): the next record takes
    # the new master's role over, re-granting it or giving it to another.
    records = list(drone.handovers)
    for i, record in enumerate(records):
        after = records[i + 1] if i + 1 < len(records) else None
        taken_over = (
            after is not None
            and after.kind == drone_pb2.HANDOVER_KIND_TAKEOVER
            and record.new_master in (after.new_master, after.old_master)
        )
        assert record.delay_s > 0 or taken_over
    assert [c.master for c in snapshot.controllers.values()].count(True) == 1


async def fly(tmp_path: Path, plan: TestbedPlan, timeout: float = 240) -> Snapshot:
    async with LocalTestbed(plan, tmp_path) as testbed:
        snapshot = await testbed.run_mission(timeout)
    assert_mission_promises(snapshot, plan)
    return snapshot


LONG_LEGS = MissionPlan(grid=2, spacing_m=100.0, altitude_m=5.0, speed_m_s=5.0, poll_s=1.0)


def long_legs_on_fast_links(
    controllers: int = 2, speedup: float = 20.0, **fields: Any
) -> TestbedPlan:
    """LONG_LEGS flown by ``controllers`` (0 master) on fast links, sped up; ``fields``:
    more of the configuration (``local_config``)."""
    config = local_config(
        controllers,
        flush_limit=0,
        speedup=speedup,
        controller_link=FAST_LINK,
        drone_link=FAST_LINK,
        **fields,
    )
    return TestbedPlan(config=config, mission=LONG_LEGS)


async def mission_errors(testbed: LocalTestbed) -> list[str]:
    """Each controller's mission error now, in controller order ("" while none)."""
    return [
        (await stub.GetStatus(ring_pb2.GetControllerStatusRequest())).mission_error
        for _, stub in sorted(testbed.controller_stubs.items())
    ]


def log_events(tmp_path: Path, part: str) -> list[dict[str, object]]:
    """The JSON log lines of one part, in order."""
    text = (tmp_path / "logs" / f"{part}.log").read_text()
    return [json.loads(line) for line in text.splitlines() if line.startswith("{")]


def three_on_fast_links() -> TestbedPlan:
    """Three controllers (0 master) on fast links at 20x, flying the small grid, with
    mutual TLS: the plan of the end-to-end security tests."""
    config = local_config(
        3, flush_limit=0, speedup=20.0, controller_link=FAST_LINK, drone_link=FAST_LINK
    )
    return TestbedPlan(config=config, mission=SMALL_GRID)


async def until_served(testbed: LocalTestbed, reqnr: int) -> None:
    """Waits until the drone served request ``reqnr``."""

    async def served() -> bool:
        return (await testbed.snapshot(audit=False)).drone.last_reqnr >= reqnr

    await eventually(served, f"request {reqnr} served", 120)


async def flying_to_the_second_waypoint(testbed: LocalTestbed) -> bool:
    """The vehicle is between waypoints 1 and 2: the mission only polls its position."""
    audit = (await testbed.snapshot()).drone.audit
    methods = [a.method.rsplit("/", 1)[1] for a in audit]
    return (
        methods.count("Goto") == 2
        and methods.count("TakePicture") == 1
        and methods[-3:] == ["GetPosition"] * 3
    )
