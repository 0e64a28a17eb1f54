"""Malformed input at every RPC, for a fixed, seeded budget (issue 11): no crash, no
hang, no change of state, and every answer a defined status, never UNKNOWN or INTERNAL
(the codes of an exception nobody handled).

The callers hold a valid certificate (an insider, or a stolen key): mutual TLS lets
them past the handshake, so the servers' own checks are what is tested. The inputs
are valid requests with bytes flipped, cut or appended, and random bytes.
"""

from __future__ import annotations

import random
from collections.abc import AsyncIterator
from pathlib import Path

import grpc
import pytest
from drone_fakes import FakeMobility
from fuzzing import INPUTS_PER_METHOD, SEED, UNHANDLED, answer, mutants

from baton.certs.make import ensure
from baton.config import controllers_only
from baton.drone.serve import build_service
from baton.drone.settings import DroneSettings
from baton.rpc.channels import aio_channel
from baton.rpc.server import BatonServer, servicer
from baton.rpc.tls import DRONE, OPERATOR, Identity, Tls
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2, drone_pb2_grpc

CONTROLLERS = (0, 1, 2)


@pytest.fixture
def certs(tmp_path: Path) -> Path:
    folder = tmp_path / "certs"
    ensure(folder, [*(Identity.controller(cid) for cid in CONTROLLERS), DRONE, OPERATOR])
    return folder


@pytest.fixture
async def drone(certs: Path) -> AsyncIterator[tuple[str, object]]:
    tls = Tls.load(certs, DRONE)
    settings = DroneSettings(config=controllers_only(CONTROLLERS), tls=tls)
    service = build_service(settings, FakeMobility())
    add = drone_pb2_grpc.add_DroneServicer_to_server
    server = BatonServer("127.0.0.1:0", [servicer("baton.v1.Drone", add, service)], tls=tls)
    await server.start()
    yield server.address, service
    await server.stop(0)


def drone_state(service: object) -> tuple[object, ...]:
    seq = service.seq  # type: ignore[attr-defined]
    return (seq.master, seq.epoch, seq.last_reqnr, seq.executed, len(seq.handovers))


async def test_malformed_requests_to_the_drone(certs: Path, drone: tuple[str, object]) -> None:
    address, service = drone
    rng = random.Random(SEED)
    goto = api.GotoRequest(latitude_deg=47.4, longitude_deg=8.5, relative_altitude_m=10)
    valid = {
        ("Invoke", False): [
            drone_pb2.InvokeRequest(
                controller_id=1, reqnr=r, method=m, payload=p, epoch=1, watermark_reqnr=r - 1
            ).SerializeToString()
            for r in (1, 2, 2**63)
            for m, p in (
                ("/baton.v1.Mobility/Goto", goto.SerializeToString()),
                ("/baton.v1.Camera/TakePicture", b""),
            )
        ],
        ("Connect", True): [
            drone_pb2.ConnectRequest(controller_id=1, holds_reqnr=3).SerializeToString()
        ],
        ("Standby", True): [drone_pb2.StandbyRequest(controller_id=1).SerializeToString()],
        ("Handover", False): [
            drone_pb2.HandoverRequest(new_master=2, takeover=True).SerializeToString()
        ],
        ("GetStatus", False): [
            drone_pb2.GetDroneStatusRequest(include_audit=True, audit_limit=5).SerializeToString()
        ],
    }
    before = drone_state(service)
    seen: dict[str, set[grpc.StatusCode]] = {}
    # As a controller that is not the master: past the handshake, not past the drone.
    async with aio_channel(address, Tls.load(certs, Identity.controller(1)), DRONE) as channel:
        for (name, stream), examples in valid.items():
            method = f"/baton.v1.Drone/{name}"
            for raw in mutants(examples, rng, INPUTS_PER_METHOD):
                code = await answer(channel, method, raw, stream)
                assert code not in UNHANDLED, (method, raw.hex(), code)
                seen.setdefault(name, set()).add(code)
        # Still serving, nothing changed.
        status = await answer(channel, "/baton.v1.Drone/GetStatus", b"", False)
        assert status is grpc.StatusCode.OK
    assert drone_state(service) == before
    assert grpc.StatusCode.INVALID_ARGUMENT in seen["GetStatus"]  # the wire format checked
    assert grpc.StatusCode.PERMISSION_DENIED in seen["Invoke"]  # another id written in
