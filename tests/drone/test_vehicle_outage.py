"""The autopilot killed with kill -9 mid-flight and restarted: seen, refused, recovered.

A real autopilot reboots, loses power, or its serial link drops. The drone
service must not serve the dead autopilot's last position as fresh (MAVSDK
keeps it, and still said "connected" for 2.4 s), must say so in GetStatus,
and must find the autopilot again, asking it for its streams again (a
rebooted ArduPilot streams nothing until asked). Whether the mission survives
is the fault-tolerance issue's; here the drone service's side is checked.
"""

from __future__ import annotations

import socket
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import grpc
import pytest
from autopilots import SKIP_REASON, Sitl, sitl_binary
from drone_harness import start_program, stop_program
from helpers.drone_bed import SPEEDUP, DroneBed, drone_bed

from baton.effects import read_effects
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class SimAutopilot:
    """The sim vehicle on a fixed port, so that a restart has the same URL."""

    def __init__(self, workdir: Path, *extra: str) -> None:
        self.workdir = workdir
        self.extra = list(extra)
        self.port = _free_udp_port()
        self.url = f"udpout://127.0.0.1:{self.port}"
        self.speedup = float(SPEEDUP)
        self.process: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        ready = self.workdir / "sim.url"
        ready.unlink(missing_ok=True)
        self.process, _ = start_program(
            [
                "sim-vehicle",
                "--port",
                str(self.port),
                "--speedup",
                SPEEDUP,
                # Armable 3 s (wall) after a start, as ArduCopter at speed-up 10 (4.7 s):
                # longer than the drone takes to find it again.
                "--warmup",
                "30",
                "--url-file",
                str(ready),
                *self.extra,
            ],
            ready,
            self.workdir / "sim.log",
        )

    def kill(self) -> None:
        assert self.process is not None
        self.process.kill()
        self.process.wait(10)

    def stop(self) -> None:
        if self.process is not None:
            stop_program(self.process)


def invoke(bed: DroneBed, reqnr: int, method: str, request: object) -> drone_pb2.InvokeReply:
    return bed.as_controller(0).Invoke(
        drone_pb2.InvokeRequest(
            controller_id=0,
            reqnr=reqnr,
            method=method,
            payload=request.SerializeToString(),  # type: ignore[attr-defined]
            epoch=1,
        ),
        timeout=15,
    )


def until(what: str, check: Callable[[], bool], timeout_s: float) -> float:
    """Polls ``check``; returns the seconds it took, fails after the deadline."""
    started = time.monotonic()
    while not check():
        assert time.monotonic() - started < timeout_s, f"{what} not within {timeout_s} s"
        time.sleep(0.05)
    return time.monotonic() - started


@pytest.mark.parametrize("kind", ["sim", pytest.param("sitl", marks=pytest.mark.sitl)])
def test_autopilot_killed_mid_flight_and_restarted(kind: str, tmp_path: Path) -> None:
    if kind == "sitl" and sitl_binary() is None:
        pytest.skip(SKIP_REASON)
    autopilot: Sitl | SimAutopilot = Sitl(tmp_path) if kind == "sitl" else SimAutopilot(tmp_path)
    autopilot.start()
    try:
        with drone_bed(tmp_path, autopilot.url, autopilot.speedup, handovers="") as bed:
            invoke(bed, 1, "/baton.v1.Mobility/Arm", api.ArmRequest())
            invoke(bed, 2, "/baton.v1.Mobility/Takeoff", api.TakeoffRequest(altitude_m=10))
            bed.wait_until("climbing", lambda s: s.position.relative_altitude_m > 3)
            healthy = bed.status().vehicle
            assert healthy.healthy and healthy.outages == 0 and healthy.stream_requests >= 1
            if isinstance(autopilot, SimAutopilot):  # PX4's MPC_XY_VEL_MAX (ArduPilot: none)
                said = bed.wait_until("its bounds read", lambda s: s.bounds[0].value == 12, 10)
                assert said.bounds[0].name == "MPC_XY_VEL_MAX"
                autopilot.extra = ["--max-speed", "7"]  # what the rebooted one says

            autopilot.kill()
            killed_at = time.monotonic()
            reqnr = 3
            while True:  # every answer after the kill is fresh, or refused
                try:
                    invoke(bed, reqnr, "/baton.v1.Mobility/GetPosition", api.GetPositionRequest())
                except grpc.RpcError as refused:
                    assert refused.code() == grpc.StatusCode.UNAVAILABLE, refused.details()
                    assert "not connected" in (refused.details() or "")
                    break
                finally:
                    reqnr += 1
                assert time.monotonic() - killed_at < 2.4, "stale position served as fresh"
                time.sleep(0.05)
            refused_after = time.monotonic() - killed_at
            down = bed.wait_until("outage reported", lambda s: not s.vehicle.healthy, 5).vehicle
            assert not bed.status().vehicle_connected and down.outages == 1
            assert "position telemetry" in down.problem or "no heartbeat" in down.problem

            autopilot.start()  # within 30 s of the kill
            assert time.monotonic() - killed_at < 30
            back = bed.wait_until("vehicle back", lambda s: s.vehicle.healthy, 60)
            assert back.vehicle.outages == 1 and back.vehicle.stream_requests >= 2  # asked again
            # What the dead autopilot said (its health, its position) is forgotten:
            # the rebooted one is not armable until its estimator is ready again.
            assert not back.flight_state.ready, "readiness of the autopilot before the kill"
            assert back.flight_state.not_ready_reason
            with pytest.raises(grpc.RpcError) as early:
                invoke(bed, reqnr, "/baton.v1.Mobility/GetPosition", api.GetPositionRequest())
            assert early.value.code() == grpc.StatusCode.UNAVAILABLE, early.value.details()
            assert "no global position" in (early.value.details() or "")
            reqnr += 1
            bed.wait_until("ready again", lambda s: s.flight_state.ready, 120)
            if isinstance(autopilot, SimAutopilot):  # the rebooted autopilot's bounds read
                bed.wait_until("its bounds read again", lambda s: s.bounds[0].value == 7, 10)
            reply = invoke(bed, reqnr, "/baton.v1.Mobility/GetPosition", api.GetPositionRequest())
            position = api.GetPositionReply.FromString(reply.payload).position
            assert position.latitude_deg != 0
            log = (tmp_path / "drone.log").read_text()
            assert "vehicle link lost" in log and "vehicle link back" in log
            print(f"{kind}: stale reads refused {refused_after:.2f} s after kill -9")
    finally:
        autopilot.stop()


@pytest.mark.parametrize("refusals", [2, 100])
def test_an_arm_refused_while_the_vehicle_reports_ready_is_asked_again(
    refusals: int, tmp_path: Path
) -> None:
    # ArduPilot SITL on a loaded CI machine refused an arm with FAILED while its
    # pre-arm bit said ready (a check failing between its 1 Hz reports), and the
    # mission's one Arm failed. The sim vehicle refuses the same way here.
    effects = tmp_path / "effects.jsonl"
    autopilot = SimAutopilot(
        tmp_path, "--arm-refusals", str(refusals), "--effects-file", str(effects)
    )
    autopilot.start()
    try:
        with drone_bed(tmp_path, autopilot.url, autopilot.speedup, handovers="") as bed:
            if refusals < 5:
                invoke(bed, 1, "/baton.v1.Mobility/Arm", api.ArmRequest())
                assert bed.status().flight_state.armed
            else:  # a vehicle that keeps refusing: the reason, after ARM_SETTLE_S
                with pytest.raises(grpc.RpcError) as refused:
                    invoke(bed, 1, "/baton.v1.Mobility/Arm", api.ArmRequest())
                assert refused.value.code() == grpc.StatusCode.ABORTED
                assert "Arm: Gyros still settling" in (refused.value.details() or "")
        arms = [e for e in read_effects(effects) if e["effect"] == "arm"]
        assert len(arms) == (1 if refusals < 5 else 0)
        log = (tmp_path / "drone.log").read_text()
        assert log.count("arm refused while the vehicle reports ready") >= min(refusals, 5)
    finally:
        autopilot.stop()
