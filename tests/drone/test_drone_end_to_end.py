"""The drone service and the sim vehicle as real processes, driven over gRPC."""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator
from pathlib import Path

import grpc
import pytest
from autopilots import Sitl
from helpers.drone_bed import EARTH_RADIUS_M, SPEEDUP, Controller, DroneBed, drone_bed

from baton.rpc.tls import DRONE
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2

# The drone's end-to-end flight on the embedded sim vehicle (or the autopilot
# at --vehicle-url), and twice in a row on one ArduPilot SITL: the second
# flight arms after the first one's landing.
VEHICLES = [
    "sim",
    pytest.param("sitl-first-flight", marks=pytest.mark.sitl),
    pytest.param("sitl-after-landing", marks=pytest.mark.sitl),
]


@pytest.fixture(params=VEHICLES)
def testbed(
    request: pytest.FixtureRequest, tmp_path: Path, vehicle_url: str | None
) -> Iterator[DroneBed]:
    if request.param == "sim":
        url, speedup = vehicle_url, float(SPEEDUP)
    else:
        sitl: Sitl = request.getfixturevalue("sitl_autopilot")
        url, speedup = sitl.url, sitl.speedup
    with drone_bed(tmp_path, url, speedup) as bed:
        yield bed


@pytest.fixture
def sim_testbed(tmp_path: Path, vehicle_url: str | None) -> Iterator[DroneBed]:
    with drone_bed(tmp_path, vehicle_url, float(SPEEDUP)) as bed:
        yield bed


def distance_m(a: api.Position, b: api.Position) -> float:
    dlat = math.radians(b.latitude_deg - a.latitude_deg)
    dlon = math.radians(b.longitude_deg - a.longitude_deg) * math.cos(math.radians(a.latitude_deg))
    return EARTH_RADIUS_M * math.hypot(dlat, dlon)


def test_mission_with_scripted_and_rpc_handovers(testbed: DroneBed) -> None:
    home = testbed.status().position
    stream = testbed.as_controller(0).Connect(drone_pb2.ConnectRequest(controller_id=0), timeout=60)
    first = next(stream)
    connected = first.connected
    assert (connected.master, connected.last_reqnr, connected.epoch) == (0, 0, 1)
    # The drone's signed grant of that epoch, which the master's log messages carry.
    assert (connected.grant.epoch, connected.grant.kind) == (1, drone_pb2.GRANT_KIND_FIRST)
    testbed.wait_until("master connected", lambda s: s.master_connected)
    c0 = Controller(testbed, 0)

    c0.invoke("/baton.v1.Mobility/Arm", api.ArmRequest(), api.ArmReply)  # 1
    testbed.wait_until("armed", lambda s: s.flight_state.armed)
    c0.invoke("/baton.v1.Mobility/Takeoff", api.TakeoffRequest(altitude_m=10), api.TakeoffReply)
    testbed.wait_until("10 m up", lambda s: s.position.relative_altitude_m > 9.5)
    position, _ = c0.invoke(
        "/baton.v1.Mobility/GetPosition", api.GetPositionRequest(), api.GetPositionReply
    )
    assert position.position.relative_altitude_m == pytest.approx(10, abs=0.6)

    target = api.GotoRequest(
        latitude_deg=home.latitude_deg + math.degrees(50 / EARTH_RADIUS_M),
        longitude_deg=home.longitude_deg,
        relative_altitude_m=10,
    )
    target_position = api.Position(
        latitude_deg=target.latitude_deg, longitude_deg=home.longitude_deg
    )
    c0.invoke("/baton.v1.Mobility/Goto", target, api.GotoReply)  # 4
    testbed.wait_until("at the target", lambda s: distance_m(s.position, target_position) < 1.0)
    position, _ = c0.invoke(
        "/baton.v1.Mobility/GetPosition", api.GetPositionRequest(), api.GetPositionReply
    )
    assert distance_m(home, position.position) == pytest.approx(50, abs=1.0)

    picture, _ = c0.invoke(
        "/baton.v1.Camera/TakePicture", api.TakePictureRequest(), api.TakePictureReply
    )
    assert 1_000_000 < len(picture.image) < 1_100_000 and picture.format == "ppm"
    assert (picture.width, picture.height, picture.sequence) == (640, 546, 1)
    assert distance_m(picture.position, target_position) < 1.0

    # Request 7 is scripted: its reply goes to the old master, then the notice.
    _, duplicate = c0.invoke("/baton.v1.Mobility/Land", api.LandRequest(), api.LandReply)
    assert not duplicate
    notice = next(stream)
    handover = drone_pb2.HandoverNotice()
    handover.CopyFrom(notice.handover)
    assert (handover.grant.master, handover.grant.epoch) == (1, 2)  # the new master's grant
    handover.ClearField("grant")
    assert handover == drone_pb2.HandoverNotice(
        old_master=0, new_master=1, after_reqnr=7, ended_epoch=1, epoch=2
    )
    assert next(stream, None) is None

    with pytest.raises(grpc.RpcError) as refused:
        c0.invoke("/baton.v1.Mobility/GetPosition", api.GetPositionRequest(), api.GetPositionReply)
    assert refused.value.code() == grpc.StatusCode.FAILED_PRECONDITION
    assert isinstance(refused.value, grpc.Call)  # the blocking stub's error is its call
    assert dict(refused.value.trailing_metadata())["baton-master"] == "1"

    # The new master re-sends the request the old one had in flight: cached.
    c1 = Controller(testbed, 1, reqnr=7, epoch=2)
    _, duplicate = c1.invoke("/baton.v1.Mobility/Land", api.LandRequest(), api.LandReply)
    assert duplicate
    testbed.wait_until(
        "landed", lambda s: s.position.relative_altitude_m < 0.3 and not s.flight_state.in_air
    )
    position, _ = c1.invoke(
        "/baton.v1.Mobility/GetPosition", api.GetPositionRequest(), api.GetPositionReply
    )
    assert position.position.relative_altitude_m < 0.3

    reply = testbed.stub.Handover(drone_pb2.HandoverRequest(new_master=2), timeout=5)
    assert reply == drone_pb2.HandoverReply(old_master=1, new_master=2, after_reqnr=8, epoch=3)
    c2 = Controller(testbed, 2, reqnr=9, epoch=3)
    c2.invoke(
        "/baton.v1.Mobility/GetFlightState", api.GetFlightStateRequest(), api.GetFlightStateReply
    )

    for method, payload, code in [
        ("/baton.v1.Mobility/Fly", b"", grpc.StatusCode.UNIMPLEMENTED),
        ("/baton.v1.Clock/Now", b"", grpc.StatusCode.UNIMPLEMENTED),
        ("/baton.v1.Mobility/Goto", b"\xff", grpc.StatusCode.INVALID_ARGUMENT),
    ]:
        with pytest.raises(grpc.RpcError) as bad:
            testbed.as_controller(2).Invoke(
                drone_pb2.InvokeRequest(
                    controller_id=2, reqnr=c2.reqnr, method=method, payload=payload, epoch=3
                ),
                timeout=5,
            )
        assert bad.value.code() == code, bad.value.details()
        c2.reqnr += 1  # a failed request is served too: its reqnr is used
    with pytest.raises(grpc.RpcError) as bad:
        testbed.as_controller(2).Invoke(
            drone_pb2.InvokeRequest(controller_id=2, reqnr=0, method="/x", epoch=3), timeout=5
        )
    assert bad.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "they start at 1" in (bad.value.details() or "")

    status = testbed.status(audit=True)
    assert status.master == 2 and status.last_reqnr == 12 and status.duplicates == 1
    methods = [entry.method.rsplit("/", 1)[1] for entry in status.audit]
    assert methods[:9] == [
        "Arm", "Takeoff", "GetPosition", "Goto", "GetPosition", "TakePicture", "Land",
        "GetPosition", "GetFlightState",
    ]  # fmt: skip
    assert [e.controller_id for e in status.audit[:9]] == [0] * 7 + [1, 2]
    assert [e.reqnr for e in status.audit] == list(range(1, 13))
    assert status.audit[5].reply_bytes > 1_000_000
    assert [(h.trigger, h.old_master, h.new_master, h.after_reqnr) for h in status.handovers] == [
        (drone_pb2.HANDOVER_TRIGGER_SCRIPT, 0, 1, 7),
        (drone_pb2.HANDOVER_TRIGGER_RPC, 1, 2, 8),
    ]
    assert all(h.delay_s > 0 and h.first_request_at > h.decided_at for h in status.handovers)


def test_grpcurl_against_the_running_drone(
    sim_testbed: DroneBed, grpcurl: Callable[..., str]
) -> None:
    testbed = sim_testbed

    def run_grpcurl(*args: str) -> str:  # as docs/operating.md shows: the operator's certificate
        return grpcurl(*args, certs=testbed.certs, peer=DRONE.dns_name)

    assert set(run_grpcurl(testbed.address, "list").split()) >= {
        "baton.v1.Drone",
        "grpc.health.v1.Health",
    }
    described = run_grpcurl(testbed.address, "describe", "baton.v1.Drone")
    for rpc in ("Invoke", "Connect", "Handover", "GetStatus"):
        assert f"rpc {rpc}" in described
    health = json.loads(
        run_grpcurl(
            "-d", '{"service": "baton.v1.Drone"}', testbed.address, "grpc.health.v1.Health/Check"
        )
    )
    assert health == {"status": "SERVING"}
    reply = json.loads(
        run_grpcurl("-d", '{"new_master": 1}', testbed.address, "baton.v1.Drone/Handover")
    )
    assert reply == {"newMaster": 1} or reply.get("new_master", reply.get("newMaster")) == 1
    status = json.loads(run_grpcurl("-d", "{}", testbed.address, "baton.v1.Drone/GetStatus"))
    assert (
        status["master"] == 1
        and status["vehicle_connected" if "vehicle_connected" in status else "vehicleConnected"]
    )
