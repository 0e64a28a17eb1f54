"""An operator's commands across real processes (the local testbed: vehicle, drone
service, controllers), each promise witnessed by the vehicle, not by baton's word (issue
32, item 4): on the sim vehicle its effects file; on ArduPilot SITL (where
``BATON_SITL_BINARY`` points at a build; helpers/vehicles.py) the autopilot's own frames
in the drone's telemetry log: its flight mode (Hold is BRAKE on ArduCopter), its speed,
and the flight commands that reached it."""

from __future__ import annotations

import asyncio
import io
import re
import time
from pathlib import Path

import grpc
import pytest
from helpers.missions import FAST_LINK, LONG_LEGS, assert_mission_promises
from helpers.testbed_runs import baton
from helpers.vehicles import VEHICLES, Tlog, gotos_served, on_vehicle
from waiting import eventually

from baton.effects import read_effects
from baton.rpc.channels import aio_channel
from baton.rpc.tls import DRONE, Identity, Tls
from baton.testbed.local import VEHICLE_EFFECTS_FILE, LocalTestbed, TestbedPlan, local_config
from baton.testbed.report import build_report
from baton.testbed.run import Progress
from baton.v1 import drone_pb2, drone_pb2_grpc, ring_pb2

SPEEDUP = 20.0
# Mission seconds: 2 wall seconds at speed-up 20; the takeover time is 3 (0.15 s wall,
# at least the 1 s detection floor). A pause outlasts both.
LOST_LINK = 40.0
OUTLASTS_S = 2 + 1
# The fastest a holding vehicle may move by its autopilot's word (GLOBAL_POSITION_INT), m/s.
STILL_M_S = 0.5


def plan(controllers: int, vehicle: str) -> TestbedPlan:
    sim = TestbedPlan(
        config=local_config(
            controllers,
            flush_limit=0,
            speedup=SPEEDUP,
            controller_link=FAST_LINK,
            drone_link=FAST_LINK,
            safety={"lost_link": LOST_LINK},
        ),
        mission=LONG_LEGS,
    )
    return on_vehicle(sim, vehicle)


def effects(tmp_path: Path) -> list[dict[str, object]]:
    return read_effects(tmp_path / VEHICLE_EFFECTS_FILE) or []


def gotos(tmp_path: Path) -> int:
    return sum(e["effect"] == "goto" for e in effects(tmp_path))


async def second_leg(testbed: LocalTestbed, tmp_path: Path, vehicle: str) -> None:
    """Waits until the vehicle flies its second leg (the sim vehicle's count, else the
    drone's)."""
    if vehicle == "sim":
        await eventually(lambda: gotos(tmp_path) >= 2, "the vehicle flying its second leg", 60)
        return

    async def served() -> bool:
        return await gotos_served(testbed) >= 2

    await eventually(served, "the vehicle flying its second leg", 60)


@pytest.mark.parametrize("vehicle", VEHICLES)
async def test_paused_the_vehicle_holds_and_no_call_reaches_it_until_resumed(
    vehicle: str, tmp_path: Path
) -> None:
    """Pause mid-mission: the vehicle holds, the master's next call waits at the drone
    (the master says why) for longer than the takeover and the lost-link times without
    either; nothing reaches the vehicle until the CLI's resume, which flies the leg on;
    the mission then completes exactly once. A controller's certificate may not pause.
    On SITL: ArduCopter says BRAKE and stands still, no flight command reaches it, and
    after the resume it says GUIDED again."""
    bed = plan(2, vehicle)
    tlog = Tlog(tmp_path)
    async with LocalTestbed(bed, tmp_path) as testbed:
        stub = testbed.drone_stub
        assert stub is not None and testbed.tls is not None
        await second_leg(testbed, tmp_path, vehicle)

        # A controller's certificate is refused, naming the rule.
        certs = tmp_path / "certs"
        as_controller = Tls.load(certs, Identity.controller(1))
        ready_file = testbed.supervisor.parts["drone"].ready_file
        assert ready_file is not None
        drone_address = ready_file.read_text().strip()  # what the drone announced
        async with aio_channel(drone_address, as_controller, DRONE) as channel:
            with pytest.raises(grpc.aio.AioRpcError) as refused:
                await drone_pb2_grpc.DroneStub(channel).Pause(drone_pb2.PauseRequest())
        assert refused.value.code() is grpc.StatusCode.PERMISSION_DENIED
        assert refused.value.details() == (
            "Pause: refused to spiffe://baton/controller/1 before reading its request: only "
            "an operator (spiffe://baton/operator) may call it on the drone's port"
        )

        before = await stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        paused = (await stub.Pause(drone_pb2.PauseRequest(note="a kite on the leg"))).command
        assert (paused.command, paused.action, paused.vehicle) == ("pause", "hold", "accepted")
        if vehicle == "sim":
            held = await eventually(
                lambda: [e for e in effects(tmp_path) if e.get("mode") == "HOLD"],
                "the vehicle holding",
                10,
            )
            held_seq = int(held[-1]["seq"])  # type: ignore[call-overload]
            held_at = float(held[-1]["time"])  # type: ignore[arg-type]
        else:  # MAVSDK's Hold is BRAKE on ArduCopter
            brake = await eventually(
                lambda: tlog.first_mode("BRAKE", after=paused.at), "ArduPilot in BRAKE", 10
            )
            held_at = brake.at
        hold_s = held_at - paused.at
        print(f"pause decided to the vehicle's HOLD: {hold_s * 1000:.1f} ms")

        # The explicit event: the master says its next request waits at the drone, and
        # why, for longer than the takeover and the lost-link times.
        master = testbed.controller_stubs[before.master]
        said = re.compile(r"waits at the drone, paused by the operator after request \d+")

        async def master_waited() -> str | None:
            # An operator's pause is expected (the operator's own doing), not a stall.
            status = await master.GetStatus(ring_pb2.GetControllerStatusRequest())
            for wait in status.waits:
                if wait.key == "paused" and said.search(wait.text) and not wait.needs_person:
                    return wait.text if wait.age_s >= OUTLASTS_S else None
            return None

        await eventually(master_waited, "the master saying why its request waits", 30)

        async def drone_says() -> bool:
            status = await stub.GetStatus(drone_pb2.GetDroneStatusRequest())
            return any(
                "the master's next request waits for Resume" in wait.text and not wait.needs_person
                for wait in status.waits
            )

        await eventually(drone_says, "the drone saying the mission is paused", 10)
        during = await stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        assert during.last_reqnr == paused.after_reqnr  # nothing admitted since the pause
        assert (during.epoch, len(during.handovers)) == (before.epoch, len(before.handovers))
        assert not during.HasField("failsafe")
        assert during.paused.after_reqnr == paused.after_reqnr
        if vehicle == "sim":
            assert [e for e in effects(tmp_path) if int(e["seq"]) > held_seq] == []  # type: ignore[call-overload]
        else:  # still braked, standing, and told nothing since it braked
            assert tlog.modes()[-1].mode == "BRAKE", tlog.modes()[-1]
            assert tlog.ground_speed_m_s() < STILL_M_S
            assert tlog.sent(after=held_at) == []
        line = io.StringIO()  # the run's progress line says it, as GetStatus does
        Progress(waypoints=4, planned_handovers=0, stream=line)(await testbed.snapshot())
        assert "| PAUSED: " in line.getvalue(), line.getvalue()

        resumed_at = time.time()
        cli = await asyncio.create_subprocess_exec(
            *baton("operator", "resume", "--address", drone_address, "--certs", str(certs)),
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
        )
        out, err = await asyncio.wait_for(cli.communicate(), 30)
        assert cli.returncode == 0, err.decode()
        assert "resume: resumed by the operator" in out.decode()
        snapshot = await testbed.run_mission(240)
    if vehicle == "sim":
        after = [e for e in effects(tmp_path) if int(e["seq"]) > held_seq]  # type: ignore[call-overload]
        assert after and after[0]["effect"] == "goto"  # the leg flown on, the resume's
    else:  # the leg flown on, in ArduCopter's command mode, only once resumed
        sent = tlog.sent(after=held_at)
        assert sent and sent[0].at > resumed_at, sent
        assert tlog.first_mode("GUIDED", after=resumed_at) is not None
    assert_mission_promises(snapshot, bed)
    commands = [(c.command, c.action, c.vehicle) for c in snapshot.drone.operator_commands]
    assert commands == [("pause", "hold", "accepted"), ("resume", "goto", "accepted")]
    report = build_report(bed.config, snapshot, grid=2, duration_s=1.0, planned_handovers=[])
    assert [c["command"] for c in report["drone"]["operator_commands"]] == ["pause", "resume"]


@pytest.mark.parametrize("vehicle", VEHICLES)
async def test_abort_returns_the_vehicle_and_every_program_ends_with_the_same_error(
    vehicle: str, tmp_path: Path
) -> None:
    """Abort (rtl) mid-mission: the vehicle returns (SITL: ArduCopter says RTL), nothing
    of the mission reaches it after that, and every controller's program ends with the
    one error the drone booked."""
    tlog = Tlog(tmp_path)
    async with LocalTestbed(plan(3, vehicle), tmp_path) as testbed:
        stub = testbed.drone_stub
        assert stub is not None
        await second_leg(testbed, tmp_path, vehicle)
        aborted = (await stub.Abort(drone_pb2.AbortRequest(action="rtl"))).command
        assert (aborted.command, aborted.action, aborted.vehicle) == ("abort", "rtl", "accepted")

        def returned() -> list[dict[str, object]]:
            return [
                e
                for e in effects(tmp_path)
                if e["effect"] == "return_to_launch" or e.get("mode") == "RETURN_TO_LAUNCH"
            ]

        if vehicle == "sim":
            await eventually(returned, "the vehicle told to return", 10)
            rtl_s = float(returned()[0]["time"]) - aborted.at  # type: ignore[arg-type]
        else:
            rtl = await eventually(
                lambda: tlog.first_mode("RTL", after=aborted.at), "ArduPilot in RTL", 10
            )
            rtl_s = rtl.at - aborted.at
        print(f"abort decided to the vehicle's return: {rtl_s * 1000:.1f} ms")

        async def every_program_ended() -> set[str] | None:
            errors = {
                (await c.GetStatus(ring_pb2.GetControllerStatusRequest())).mission_error
                for c in testbed.controller_stubs.values()
            }
            return errors if "" not in errors else None

        errors = await eventually(every_program_ended, "every program ended by the abort", 60)
        status = await stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        with pytest.raises(grpc.aio.AioRpcError) as again:
            await stub.Resume(drone_pb2.ResumeRequest())
    [error] = errors  # the same on every controller: the drone's booked refusal, logged
    assert (
        f"the mission has ended (aborted by the operator after request {aborted.after_reqnr}: rtl)"
        in error
    )
    assert error.endswith("nothing was executed")
    assert status.ended.command == "abort" and status.last_reqnr > aborted.after_reqnr
    if vehicle == "sim":
        first = int(returned()[0]["seq"])  # type: ignore[call-overload]
        assert [e["effect"] for e in effects(tmp_path) if int(e["seq"]) > first] == []  # type: ignore[call-overload]
    else:  # after the return (or its repeats) nothing of the mission reached ArduPilot
        sent = tlog.sent()
        first = next(i for i, c in enumerate(sent) if c.returns and c.at >= aborted.at)
        assert [c.what for c in sent[first:] if not c.returns] == [], sent
    assert again.value.code() is grpc.StatusCode.FAILED_PRECONDITION
    assert "the mission has ended" in (again.value.details() or "")
