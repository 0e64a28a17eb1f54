"""The mission's geofence across real processes (the local testbed: vehicle, drone
service, controllers), witnessed by the vehicle, not by baton's word (issue 32, item
3): on the sim vehicle its effects file, on ArduPilot SITL (where
``BATON_SITL_BINARY`` points at a build) the drone's telemetry log of the autopilot's
own frames. The mission is tests/drone/missions/fenced.py in an L-shaped fence."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest
from autopilots import SKIP_REASON, sitl_binary
from helpers.missions import FAST_LINK
from helpers.vehicles import Tlog
from pymavlink import mavutil
from waiting import eventually

from baton.effects import read_effects
from baton.sdk import Position
from baton.sdk.geo import north_east_m, offset
from baton.testbed.local import (
    VEHICLE_EFFECTS_FILE,
    LocalTestbed,
    TestbedPlan,
    local_config,
)
from baton.v1 import drone_pb2

MISSIONS = Path(__file__).parent / "missions"
SPEEDUP = 20.0
ARM_M = 30.0  # the L's arms are 2 * ARM_M wide
HOME = Position(47.397742, 8.545594, 488.0)
# (north, east) metres from home: the corner around home, an arm up to 230 m north and
# one 230 m east; the mission flies 200 m up one, then to 200 m along the other.
L_SHAPE = [(-30, -30), (-30, 230), (30, 230), (30, 30), (230, 30), (230, -30)]
OUT_NORTH_M = 400.0  # the refused Goto's target (fenced.py's OUT_M)


def corner(north: float, east: float) -> list[float]:
    p = offset(HOME, north, east)
    return [p.latitude_deg, p.longitude_deg]


def fenced_plan(vehicle: str) -> TestbedPlan:
    return TestbedPlan(
        config=local_config(
            3,
            flush_limit=0,
            speedup=SPEEDUP,
            controller_link=FAST_LINK,
            drone_link=FAST_LINK,
            safety={
                "fence": {"polygon": [corner(n, e) for n, e in L_SHAPE], "ceiling": 60},
                "lost_link": 0,
            },
        ),
        mission_file=MISSIONS / "fenced.py",
        vehicle=vehicle,
        sitl_binary=sitl_binary() if vehicle == "sitl" else None,
    )


# The breach races the autopilot's own fence action (GF_ACTION, set with the upload)
# against the drone's look at the vehicle's position: whichever acts first, the mission
# ends in failsafe, the drone's fence failsafe or the autopilot's takeover.
@pytest.mark.parametrize("vehicle", ["sim", pytest.param("sitl", marks=pytest.mark.sitl)])
async def test_a_goto_out_of_the_fence_is_refused_and_a_breach_returns_the_vehicle(
    vehicle: str, tmp_path: Path
) -> None:
    """The vehicle holds the uploaded fence before it arms; the Goto out of it never
    reaches the vehicle, and every controller's program sees it refused; the leg that
    cuts the L's inner corner leaves the fence, the drone returns the vehicle (the
    fence's rtl) and every program ends with the same failsafe error."""
    if vehicle == "sitl" and sitl_binary() is None:
        pytest.skip(SKIP_REASON)
    plan = fenced_plan(vehicle)
    async with LocalTestbed(plan, tmp_path) as testbed:
        assert testbed.drone_stub is not None
        snapshot = await testbed.run_mission(180)
        status = await testbed.drone_stub.GetStatus(drone_pb2.GetDroneStatusRequest())
    errors = {c.mission_error for c in snapshot.controllers.values()}
    assert len(errors) == 1, errors
    (error,) = errors
    if status.failsafe.cause == "fence":
        assert "in failsafe (fence: fence breach: the vehicle at (" in error, error
        assert "is outside the inclusion polygon of 6 vertices: rtl)" in error
    else:  # the autopilot returned the vehicle before the drone saw it outside
        assert "in failsafe (autopilot: autopilot took over: " in error, error
    # Every replica's program saw the same replies, the refusal among them.
    assert len({c.reply_chain for c in snapshot.controllers.values()}) == 1
    logs = {cid: (tmp_path / "logs" / f"controller-{cid}.log").read_text() for cid in (0, 1, 2)}
    for cid, text in logs.items():
        assert "failed with OUT_OF_RANGE: Mobility.Goto to (" in text, f"controller {cid}"
        assert "is outside the mission's fence (outside the inclusion polygon" in text
    assert (status.failsafe.cause, status.failsafe.action) in (
        ("fence", "rtl"),
        ("autopilot", "RETURN_TO_LAUNCH" if vehicle == "sim" else "RTL"),
    ), status.failsafe
    drone_log = (tmp_path / "logs" / "drone.log").read_text()
    assert '"fence uploaded"' in drone_log
    if vehicle == "sim":
        flown = read_effects(tmp_path / VEHICLE_EFFECTS_FILE)
        kinds = [e["effect"] for e in flown]
        assert "fence" in kinds and kinds.index("fence") < kinds.index("arm"), kinds
        held = next(e for e in flown if e["effect"] == "fence")
        # As MAVLink carries them: degrees times 1e7, whole.
        sent = [[round(x, 7) for x in corner(n, e)] for n, e in L_SHAPE]
        assert held["polygons"] == [sent]
        gotos = [
            north_east_m(HOME, Position(e["latitude_deg"], e["longitude_deg"]))
            for e in flown
            if e["effect"] == "goto"
        ]
        # North, then east; never the refused one north of the fence.
        assert [(round(n), round(e)) for n, e in gotos] == [(200, 0), (0, 200)], gotos
        last_goto = max(e["seq"] for e in flown if e["effect"] == "goto")
        returned = [
            e
            for e in flown
            if e["seq"] > last_goto
            and (
                e["effect"] in ("return_to_launch", "fence_breach")  # the drone's, its own
                or e.get("mode") == "RETURN_TO_LAUNCH"
            )
        ]
        assert returned, kinds
    else:
        # The autopilot accepted the fence upload, and its own positions never went
        # beyond the north arm's end towards the refused target.
        tlog = Tlog(tmp_path)
        acks = tlog.messages("MISSION_ACK")
        fence_type = mavutil.mavlink.MAV_MISSION_TYPE_FENCE
        assert any(
            a.mission_type == fence_type and a.type == mavutil.mavlink.MAV_MISSION_ACCEPTED
            for a in acks
        ), acks
        norths = [
            north_east_m(HOME, Position(m.lat / 1e7, m.lon / 1e7))[0]
            for m in tlog.messages("GLOBAL_POSITION_INT")
            if m.lat or m.lon
        ]
        assert norths and max(norths) < 240.0 < OUT_NORTH_M


@pytest.mark.slow  # ~30 s; tests/sim_vehicle/test_fence_upload.py covers it in-process
async def test_the_fence_is_uploaded_again_after_a_drone_restart(tmp_path: Path) -> None:
    """kill -9 of the drone once the vehicle flies, restarted on its state file: the
    restarted drone uploads the fence again at connect (the sim vehicle counts a second
    upload)."""
    plan = fenced_plan("sim")
    effects = tmp_path / VEHICLE_EFFECTS_FILE
    async with LocalTestbed(plan, tmp_path) as testbed:

        def uploads() -> int:
            return sum(e["effect"] == "fence" for e in read_effects(effects))

        await eventually(
            lambda: any(e["effect"] == "goto" for e in read_effects(effects)),
            "the vehicle flying its first leg",
            60,
        )
        assert uploads() == 1
        part = testbed.supervisor.parts["drone"]
        assert part.process is not None and part.ready_file is not None
        os.kill(part.process.pid, signal.SIGKILL)
        await part.process.wait()
        restarted = await testbed.supervisor.start("drone", part.argv, part.ready_file)
        await testbed.supervisor.wait_ready(restarted)
        await eventually(lambda: uploads() == 2, "the fence uploaded again", 30)
