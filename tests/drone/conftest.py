"""Fixtures: a drone service over the fake vehicle, served in-process on a real port."""

from __future__ import annotations

from collections.abc import AsyncIterator
from dataclasses import dataclass

import pytest
from baton.drone.master import parse_handover_script
from baton.drone.service import DroneService, DroneSettings, build_service
from baton.rpc.channels import aio_channel
from baton.rpc.server import BatonServer
from baton.v1 import drone_pb2_grpc
from drone_fakes import FakeMobility


@dataclass
class DroneUnderTest:
    """The servicer, its fake vehicle and a stub over a real channel."""

    service: DroneService
    vehicle: FakeMobility
    stub: drone_pb2_grpc.DroneStub
    address: str


async def start_drone(script: str = "", **settings: object) -> tuple[DroneUnderTest, BatonServer]:
    """A drone for controllers 0, 1, 2 (master 0) on a free port."""
    controllers = (0, 1, 2)
    defaults: dict[str, object] = {
        "address": "127.0.0.1:0",
        "controllers": controllers,
        "resolution": (64, 48),
        "handover_script": parse_handover_script(script, "script", controllers),
    }
    vehicle = FakeMobility()
    service = build_service(DroneSettings(**{**defaults, **settings}), vehicle)  # type: ignore[arg-type]
    server = BatonServer("127.0.0.1:0", ["baton.v1.Drone"])
    drone_pb2_grpc.add_DroneServicer_to_server(service, server.server)
    await server.start()
    stub = drone_pb2_grpc.DroneStub(aio_channel(server.address))
    return DroneUnderTest(service, vehicle, stub, server.address), server


@pytest.fixture
async def drone() -> AsyncIterator[DroneUnderTest]:
    under_test, server = await start_drone()
    yield under_test
    await server.stop(0)
