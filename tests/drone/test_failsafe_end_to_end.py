"""The operator's safety net across real processes (the local testbed: vehicle, drone
service, controllers), each promise witnessed by the vehicle, not by baton's word (issue
32, items 1, 2, 6 and 7): on the sim vehicle its effects file; on ArduPilot SITL (where
``BATON_SITL_BINARY`` points at a build; helpers/vehicles.py) the autopilot's own frames
in the drone's telemetry log, or a monitor on its second port while the drone is dead."""

from __future__ import annotations

import io
import os
import signal
import time
from dataclasses import replace
from pathlib import Path

import pytest
from autopilots import TelemetryMonitor
from helpers.missions import (
    FAST_LINK,
    LONG_LEGS,
    flying_to_the_second_waypoint,
    log_events,
    long_legs_on_fast_links,
    mission_errors,
)
from helpers.pilot import PX4_AUTO_RTL, switch_ardupilot_mode, switch_mode
from helpers.vehicles import VEHICLES, Tlog, gotos_served, on_vehicle
from waiting import eventually

from baton.drone.safety import FROM_AUTOPILOT
from baton.effects import read_effects
from baton.testbed.local import VEHICLE_EFFECTS_FILE, LocalTestbed, TestbedPlan, local_config
from baton.testbed.report import build_report
from baton.testbed.run import Progress
from baton.v1 import drone_pb2

MISSIONS = Path(__file__).parent / "missions"
SPEEDUP = 20.0
LOST_LINK_S = 60.0  # mission seconds: 3 wall seconds at speed-up 20
# SITL's battery for the reserve test: ArduPilot's remaining percentage is its consumed
# charge against BATT_CAPACITY, and SITL's "+" copter draws about 29 A in a hover (its
# frame model's reference current), so 1000 mAh is about 2 minutes of flight: the sim
# vehicle's 8 Wh. SITL's own battery stays unlimited (SIM_BATT_CAP_AH 0): the voltage
# holds, and no voltage failsafe of the autopilot's races the drone's reserve.
SITL_BATTERY = (("BATT_CAPACITY", 1000.0),)


@pytest.mark.parametrize("vehicle", VEHICLES)
async def test_every_station_killed_mid_flight_is_the_failsafe_after_lost_link(
    vehicle: str, tmp_path: Path
) -> None:
    """Every controller killed while the vehicle flies a leg: after lost_link the drone
    commands the configured action (rtl), the vehicle counts it (SITL: ArduPilot says RTL
    in its heartbeat), GetStatus says why; an operator's Resume clears it."""
    plan = TestbedPlan(
        config=local_config(
            3,
            flush_limit=0,
            speedup=SPEEDUP,
            controller_link=FAST_LINK,
            drone_link=FAST_LINK,
            safety={"lost_link": LOST_LINK_S, "lost_link_action": "rtl"},
        ),
        mission=LONG_LEGS,
    )
    plan = on_vehicle(plan, vehicle)
    async with LocalTestbed(plan, tmp_path) as testbed:
        assert testbed.drone_stub is not None
        effects = tmp_path / VEHICLE_EFFECTS_FILE
        tlog = Tlog(tmp_path)

        def gotos() -> int:
            return sum(e["effect"] == "goto" for e in read_effects(effects))

        if vehicle == "sim":
            await eventually(lambda: gotos() >= 2, "the vehicle flying its second leg", 60)
        else:

            async def second_leg() -> bool:
                return await gotos_served(testbed) >= 2

            await eventually(second_leg, "the vehicle flying its second leg", 60)
        for cid in (0, 1, 2):
            process = testbed.supervisor.parts[f"controller-{cid}"].process
            assert process is not None
            os.kill(process.pid, signal.SIGKILL)
        killed_at = time.time()

        def returned() -> list[dict[str, object]]:
            return [
                e
                for e in read_effects(effects)
                if e["effect"] == "return_to_launch"  # MAV_CMD_NAV_RETURN_TO_LAUNCH, or
                or e.get("mode") == "RETURN_TO_LAUNCH"  # PX4's mode, as MAVSDK sets it
            ]

        if vehicle == "sim":
            await eventually(lambda: bool(returned()), "the vehicle told to return", 30)
            acted_after_s = float(returned()[0]["time"]) - killed_at  # type: ignore[arg-type]
        else:  # ArduCopter's own heartbeat saying RTL (custom_mode 6), as the drone heard it
            rtl = await eventually(
                lambda: tlog.first_mode("RTL", after=killed_at), "ArduPilot in RTL", 30
            )
            acted_after_s = rtl.at - killed_at
        print(
            f"lost link to rtl at the vehicle: {acted_after_s:.2f} s wall, "
            f"{acted_after_s * SPEEDUP:.1f} mission s (lost_link {LOST_LINK_S:g})"
        )
        assert LOST_LINK_S / SPEEDUP <= acted_after_s < LOST_LINK_S / SPEEDUP + 3.0
        status = await testbed.drone_stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        assert status.HasField("failsafe")
        assert (status.failsafe.cause, status.failsafe.action) == ("lost_link", "rtl")
        assert "no usable controller" in status.failsafe.reason
        assert status.lost_link_s == LOST_LINK_S / SPEEDUP
        cleared = await testbed.drone_stub.Resume(drone_pb2.ResumeRequest())
        assert cleared.cleared.cause == "lost_link"
        status = await testbed.drone_stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        assert not status.HasField("failsafe")
    log = (tmp_path / "logs" / "drone.log").read_text()
    assert '"failsafe"' in log and "failsafe cleared by the operator" in log


async def test_a_speed_and_a_sleep_beyond_the_bounds_are_refused_and_nothing_executed(
    tmp_path: Path,
) -> None:
    """The sim vehicle says MPC_XY_VEL_MAX = 8 (under safety.max_speed = 15): GetStatus
    shows it as the speed bound in force, read from the autopilot; SetSpeed(1e9) and
    SetSpeed(10) are refused INVALID_ARGUMENT naming it, and the vehicle never told
    either; Sleep(1e12) refused naming safety.max_sleep; SetSpeed(3) reaches it."""
    plan = TestbedPlan(
        config=local_config(2, flush_limit=0, speedup=SPEEDUP),
        mission_file=MISSIONS / "beyond_bounds.py",
        vehicle_args=("--max-speed", "8"),
    )
    async with LocalTestbed(plan, tmp_path) as testbed:
        assert testbed.drone_stub is not None
        stub = testbed.drone_stub

        async def bounds() -> dict[str, drone_pb2.FlightBound]:
            status = await stub.GetStatus(drone_pb2.GetDroneStatusRequest())
            return {b.bound: b for b in status.bounds}

        async def vehicle_said() -> bool:
            return (await bounds())["max_speed"].name == "MPC_XY_VEL_MAX"

        await eventually(vehicle_said, "the drone read the vehicle's MPC_XY_VEL_MAX", 30)
        said = await bounds()
        assert (said["max_speed"].value, said["max_speed"].source) == (8.0, FROM_AUTOPILOT)
        assert (said["max_altitude"].name, said["max_altitude"].value) == (
            "safety.max_altitude",
            120.0,
        )
        await testbed.run_mission(120)
    speeds = [
        e["speed_m_s"]
        for e in read_effects(tmp_path / VEHICLE_EFFECTS_FILE)
        if e["effect"] == "set_speed"
    ]
    assert speeds == [3.0]  # the sane one only: 1e9 and 10 never reached the vehicle
    logs = " ".join(p.read_text() for p in (tmp_path / "logs").glob("*.log"))
    assert "speed_m_s 10 is beyond the vehicle's bound MPC_XY_VEL_MAX = 8 (read from" in logs
    assert "safety.max_sleep = 600" in logs


async def test_the_cruise_speed_survives_a_drone_killed_mid_mission(tmp_path: Path) -> None:
    """kill -9 of the drone mid-mission, restarted on its state file: every goto the
    vehicle flies after the restart is followed by the mission's speed, as before it
    (issue 32, item 6; ArduPilot resets the speed at every reposition). The autopilot's
    own GCS failsafe is given 10 min: a loaded restart may outlast its 5 s wall floor."""
    plan = long_legs_on_fast_links(2, SPEEDUP, safety={"autopilot_gcs_timeout": "10min"})
    effects = tmp_path / VEHICLE_EFFECTS_FILE
    async with LocalTestbed(plan, tmp_path) as testbed:

        def gotos() -> int:
            return sum(e["effect"] == "goto" for e in read_effects(effects))

        await eventually(lambda: gotos() >= 2, "the vehicle flying its second leg", 60)
        # Killed while the mission only polls the position: a Goto the kill cuts off is
        # booked as its outcome (the vehicle may have acted) and ends the mission.
        await eventually(
            lambda: flying_to_the_second_waypoint(testbed), "the vehicle between waypoints"
        )
        part = testbed.supervisor.parts["drone"]
        assert part.process is not None and part.ready_file is not None
        os.kill(part.process.pid, signal.SIGKILL)
        await part.process.wait()
        killed_at_seq = max(e["seq"] for e in read_effects(effects))
        restarted = await testbed.supervisor.start("drone", part.argv, part.ready_file)
        await testbed.supervisor.wait_ready(restarted)
        await testbed.run_mission(240)
    flown = read_effects(effects)
    after = [e for e in flown if e["seq"] > killed_at_seq]
    gotos_after = [i for i, e in enumerate(after) if e["effect"] == "goto"]
    assert gotos_after, "no goto after the restart"
    for i in gotos_after:
        following = after[i + 1] if i + 1 < len(after) else None
        assert following is not None and following["effect"] == "set_speed", after
        assert following["speed_m_s"] == LONG_LEGS.speed_m_s
    log = (tmp_path / "logs" / "drone.log").read_text()
    assert "cruise speed restored" in log


@pytest.mark.parametrize("vehicle", VEHICLES)
async def test_a_drained_battery_ends_the_mission_with_a_return(
    vehicle: str, tmp_path: Path
) -> None:
    """A small battery (8 Wh: about 2 min of flight; SITL: SITL_BATTERY) and an 80 %
    reserve: early in the mission the drone commands the return, the vehicle counts it
    (SITL: ArduPilot, having said it was below 80 %, says RTL), and the program's next
    call fails FAILED_PRECONDITION on every controller (issue 32, item 2). The reserve is
    crossed early so that a loaded machine's late battery reading still falls while the
    vehicle flies (at 50 % it fell after the last waypoint, with the vehicle landing)."""
    plan = TestbedPlan(
        config=local_config(
            2,
            flush_limit=0,
            speedup=SPEEDUP,
            controller_link=FAST_LINK,
            drone_link=FAST_LINK,
            safety={"battery_reserve": 80.0, "battery_action": "rtl"},
        ),
        mission=LONG_LEGS,
        vehicle_args=("--battery-capacity-wh", "8"),
        sitl_params=SITL_BATTERY,
    )
    plan = on_vehicle(plan, vehicle)
    async with LocalTestbed(plan, tmp_path) as testbed:
        assert testbed.drone_stub is not None
        effects = tmp_path / VEHICLE_EFFECTS_FILE
        tlog = Tlog(tmp_path)

        def returned() -> list[dict[str, object]]:
            return [
                e
                for e in read_effects(effects)
                if e["effect"] == "return_to_launch" or e.get("mode") == "RETURN_TO_LAUNCH"
            ]

        if vehicle == "sim":
            await eventually(lambda: bool(returned()), "the vehicle told to return", 120)
        else:
            rtl = await eventually(lambda: tlog.first_mode("RTL"), "ArduPilot in RTL", 120)
            # The autopilot's own estimate crossed the reserve before it returned.
            said = [pct for at, pct in tlog.battery_remaining() if at <= rtl.at]
            assert said and min(said) < 80 <= max(said), said
        status = await testbed.drone_stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        assert (status.failsafe.cause, status.failsafe.action) == ("battery", "rtl")
        assert "below the reserve of 80 %" in status.failsafe.reason
        # The operator sees it where a run shows it: the progress line and the report.
        snapshot = await testbed.snapshot()
        line = io.StringIO()
        Progress(waypoints=4, planned_handovers=0, stream=line)(snapshot)
        assert "| FAILSAFE rtl: " in line.getvalue() and "80 %" in line.getvalue()
        report = build_report(plan.config, snapshot, grid=2, duration_s=1.0, planned_handovers=[])
        assert (report["drone"]["failsafe"]["cause"], report["drone"]["failsafe"]["action"]) == (
            "battery",
            "rtl",
        )
        # Nothing after the return reached the vehicle: every later call refused.
        if vehicle == "sim":
            first = int(returned()[0]["seq"])  # type: ignore[call-overload]
            assert [e["effect"] for e in read_effects(effects) if e["seq"] > first] == []
        else:
            sent = tlog.sent()
            first = next(i for i, c in enumerate(sent) if c.returns)
            assert [c.what for c in sent[first:] if not c.returns] == [], sent

        async def every_program_told() -> bool:
            errors = await mission_errors(testbed)
            return all("in failsafe (battery" in error for error in errors)

        await eventually(every_program_told, "every program ended by the failsafe", 60)


@pytest.mark.parametrize("vehicle", VEHICLES)
async def test_the_drone_service_dead_the_autopilot_returns_and_a_restart_ends_the_mission(
    vehicle: str, tmp_path: Path
) -> None:
    """kill -9 of the drone mid-leg: the autopilot's own GCS failsafe (PX4's NAV_DLL_ACT
    and COM_DL_LOSS_T; ArduPilot's FS_GCS_ENABLE, FS_GCS_TIMEOUT and SYSID_MYGCS; set by
    the drone at connect) returns the vehicle once no ground station was heard for the
    timeout (5 s of wall time at least), and lands it. The drone restarted only then
    holds the vehicle it had seen in the air to it (the state file keeps that), so its
    first sight of it on the ground is the autopilot failsafe, and every program is told.
    Before, the mission polled for a waypoint the landed vehicle would never reach, and
    the drone blamed a controller's standby stream. On SITL the witness is a monitor on
    its second port (the drone's telemetry log dies with the drone), a ground station
    ArduPilot does not count as its own (SYSID_MYGCS names the drone's)."""
    plan = on_vehicle(long_legs_on_fast_links(2, SPEEDUP), vehicle)
    effects = tmp_path / VEHICLE_EFFECTS_FILE
    monitor: TelemetryMonitor | None = None
    async with LocalTestbed(plan, tmp_path) as testbed:
        if vehicle == "sitl":
            assert testbed.sitl_monitor_url is not None
            monitor = TelemetryMonitor(testbed.sitl_monitor_url, speedup=SPEEDUP)
            monitor.start()
        await eventually(
            lambda: flying_to_the_second_waypoint(testbed), "the vehicle between waypoints", 60
        )
        log = (tmp_path / "logs" / "drone.log").read_text()
        set_by_the_drone = "NAV_DLL_ACT=2" if vehicle == "sim" else "FS_GCS_ENABLE=1"
        assert '"autopilot GCS failsafe set"' in log and set_by_the_drone in log
        await testbed.supervisor.kill("drone")
        killed_at = time.time()

        def returned() -> list[dict[str, object]]:
            return [e for e in read_effects(effects) if e["effect"] == "link_loss_return"]

        def landed() -> bool:
            states = [e for e in log_events(tmp_path, "sim-vehicle") if "phase" in e]
            return (
                bool(returned()) and states[-1]["phase"] == "on_ground" and not states[-1]["armed"]
            )

        if monitor is None:
            await eventually(landed, "the autopilot returning and landing by itself", 60)
            after_s = float(returned()[0]["time"]) - killed_at  # type: ignore[arg-type]
        else:  # ArduCopter's RTL lands at home and disarms there, still in RTL
            sitl = monitor

            def rtl_then_disarmed() -> float | None:
                rtl = next((r for r in sitl.modes if r.mode == "RTL" and r.at > killed_at), None)
                if rtl is None or sitl.modes[-1].armed:
                    return None
                return rtl.at

            returned_at = await eventually(
                rtl_then_disarmed, "ArduPilot returning and landing by itself", 120
            )
            after_s = returned_at - killed_at
        print(f"drone killed to the autopilot's return: {after_s:.2f} s wall")
        # Counted from the last GCS heartbeat the vehicle heard (sent each second, up to
        # 1 s before the kill, more on a loaded machine), not from the kill.
        assert after_s >= 5.0 - 1.5
        await testbed.supervisor.restart("drone")

        async def every_program_told() -> list[str]:
            errors = await mission_errors(testbed)
            told = all("the vehicle landed while the drone service was down" in e for e in errors)
            return errors if told else []

        errors = await eventually(every_program_told, "every program ended by the landing", 60)
        assert len(set(errors)) == 1, errors
        assert testbed.drone_stub is not None
        status = await testbed.drone_stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        assert (status.failsafe.cause, status.failsafe.action) == ("autopilot", "landed")
    if monitor is not None:
        monitor.stop()


@pytest.mark.parametrize("vehicle", VEHICLES)
async def test_the_autopilot_returning_on_its_own_is_a_failsafe(
    vehicle: str, tmp_path: Path
) -> None:
    """A mode switch the drone did not send (a pilot's, as the autopilot's own failsafe
    or fence action would be) while the vehicle flies a leg: the drone enters the
    autopilot failsafe and commands nothing more; the program's next call fails with it
    on every controller alike (before, the mission polled for a target it never
    reached); GetStatus says what the autopilot did; an operator's Resume clears it.
    On SITL the pilot switches ArduCopter to RTL through its second port, and the
    drone names the mode as ArduPilot does (RTL)."""
    plan = on_vehicle(long_legs_on_fast_links(2, SPEEDUP), vehicle)
    effects = tmp_path / VEHICLE_EFFECTS_FILE
    tlog = Tlog(tmp_path)
    mode = "RETURN_TO_LAUNCH" if vehicle == "sim" else "RTL"
    async with LocalTestbed(plan, tmp_path) as testbed:
        assert testbed.drone_stub is not None
        await eventually(
            lambda: flying_to_the_second_waypoint(testbed), "the vehicle between waypoints", 60
        )
        status = await testbed.drone_stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        if vehicle == "sim":
            await switch_mode(status.vehicle_url, PX4_AUTO_RTL)
            switched = [e for e in read_effects(effects) if e.get("mode") == "RETURN_TO_LAUNCH"]
            assert len(switched) == 1, switched
            switched_at = float(switched[0]["time"])  # type: ignore[arg-type]
        else:
            assert testbed.sitl_monitor_url is not None
            asked_at = time.time()
            await switch_ardupilot_mode(testbed.sitl_monitor_url, "RTL")
            # When the drone heard ArduPilot say it: the drone cannot decide before that.
            rtl = await eventually(
                lambda: tlog.first_mode("RTL", after=asked_at), "ArduPilot saying RTL", 10
            )
            switched_at = rtl.at

        async def every_program_told() -> list[str]:
            errors = await mission_errors(testbed)
            told = all("in failsafe (autopilot: autopilot took over: " in e for e in errors)
            return errors if told else []

        errors = await eventually(every_program_told, "every program ended by the takeover", 60)
        assert mode in errors[0] and len(set(errors)) == 1, errors
        told_after_s = time.time() - switched_at
        status = await testbed.drone_stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        assert (status.failsafe.cause, status.failsafe.action) == ("autopilot", mode)
        decided_after_s = status.failsafe.since - switched_at
        print(
            f"autopilot's RTL to the drone's failsafe: {decided_after_s:.2f} s wall; "
            f"every program told within {told_after_s:.2f} s"
        )
        assert 0 <= decided_after_s < 2.0
        # The drone commanded the vehicle nothing after the switch: no goto, no hold.
        if vehicle == "sim":
            after = [e["effect"] for e in read_effects(effects) if e["seq"] > switched[0]["seq"]]
            assert after == [], after
        else:
            assert tlog.sent(after=switched_at) == []
        cleared = await testbed.drone_stub.Resume(drone_pb2.ResumeRequest())
        assert cleared.cleared.cause == "autopilot"
    log = (tmp_path / "logs" / "drone.log").read_text()
    assert '"failsafe"' in log and f"autopilot took over: {mode}" in log


async def test_a_picture_re_sent_to_a_restarted_drone_waits_for_the_vehicle(
    tmp_path: Path,
) -> None:
    """kill -9 of the drone after the Goto and before the picture (the mission sleeps at
    the waypoint meanwhile), restarted while the vehicle's process is stopped: the
    restarted drone does not know where the vehicle is, so the picture it is sent is
    refused UNAVAILABLE (nothing taken, the number unused), not taken with no place.
    Once the vehicle is back and looked at, the picture is taken at the waypoint, once.
    The autopilot's GCS failsafe is given 10 min: the vehicle stays where it was sent."""
    plan = replace(
        long_legs_on_fast_links(2, SPEEDUP, safety={"autopilot_gcs_timeout": "10min"}),
        mission_file=MISSIONS / "picture_after_a_wait.py",
    )
    pictures = tmp_path / "camera-effects.jsonl"
    async with LocalTestbed(plan, tmp_path) as testbed:

        async def waiting_at_the_waypoint() -> bool:
            audit = (await testbed.snapshot()).drone.audit
            return bool(audit) and audit[-1].method.endswith("/Goto")

        await eventually(waiting_at_the_waypoint, "the Goto served, the mission waiting", 60)
        supervisor = testbed.supervisor
        drone = supervisor.parts["drone"]
        assert drone.process is not None
        os.kill(drone.process.pid, signal.SIGKILL)
        await drone.process.wait()
        assert read_effects(pictures) == []  # the premise: the picture comes next
        supervisor.freeze("sim-vehicle")
        await supervisor.restart("drone")

        def picture_asked() -> str:
            for event in log_events(tmp_path, "drone"):
                if str(event.get("method", "")).endswith("/TakePicture"):
                    return str(event.get("msg"))
            return ""

        first = await eventually(picture_asked, "the picture asked of the restarted drone", 60)
        assert first == "invoke rejected", read_effects(pictures)
        supervisor.thaw("sim-vehicle")
        snapshot = await testbed.run_mission(120)
    errors = [c.mission_error for c in snapshot.controllers.values()]
    assert errors == ["", ""], errors
    [picture] = read_effects(pictures)
    assert "latitude_deg" in picture, picture  # taken where the vehicle was known to be
    rejected = [e for e in log_events(tmp_path, "drone") if e.get("msg") == "invoke rejected"]
    assert {e["code"] for e in rejected} == {"UNAVAILABLE"}, rejected
