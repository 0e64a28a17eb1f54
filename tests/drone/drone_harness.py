"""Starting drone services for tests: in-process over the fake vehicle, or as processes."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from drone_fakes import FakeMobility

from baton.config import controllers_only
from baton.drone.master import parse_handover_script
from baton.drone.serve import build_service
from baton.drone.service import DroneService
from baton.drone.settings import DroneSettings
from baton.rpc.channels import aio_channel
from baton.rpc.server import BatonServer, servicer
from baton.rpc.streams import next_message
from baton.v1 import drone_pb2, drone_pb2_grpc


@dataclass
class DroneUnderTest:
    """The servicer, its fake vehicle and a stub over a real channel."""

    service: DroneService
    vehicle: FakeMobility
    stub: drone_pb2_grpc.DroneAsyncStub
    address: str


async def start_drone(script: str = "", **settings: object) -> tuple[DroneUnderTest, BatonServer]:
    """A drone for controllers 0, 1, 2 (master 0) on a free port; ``vehicle=`` a
    FakeMobility to drive it (a restarted drone's is its predecessor's), else a new one."""
    controllers = (0, 1, 2)
    defaults: dict[str, object] = {
        "config": controllers_only(controllers),
        "resolution": (64, 48),
        "handover_script": parse_handover_script(script, "script", controllers),
    }
    vehicle = settings.pop("vehicle", None) or FakeMobility()
    assert isinstance(vehicle, FakeMobility)
    service = build_service(DroneSettings(**{**defaults, **settings}), vehicle)  # type: ignore[arg-type]
    add = drone_pb2_grpc.add_DroneServicer_to_server
    server = BatonServer("127.0.0.1:0", [servicer("baton.v1.Drone", add, service)])
    await server.start()
    stub = drone_pb2_grpc.DroneStub(aio_channel(server.address))
    return DroneUnderTest(service, vehicle, stub, server.address), server


def start_program(
    args: list[str], ready_file: Path, log: Path, timeout_s: float = 20
) -> tuple[subprocess.Popen[bytes], str]:
    """Starts ``baton ARGS``, waits for ``ready_file``; returns the process and its first line."""
    with log.open("wb") as err:
        process = subprocess.Popen(
            [sys.executable, "-m", "baton.cli", *args],
            stdout=subprocess.DEVNULL,
            stderr=err,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
    deadline = time.monotonic() + timeout_s
    while not ready_file.exists():
        if process.poll() is not None:
            raise RuntimeError(
                f"baton {args[0]} exited with {process.returncode}: {log.read_text()}"
            )
        if time.monotonic() > deadline:
            process.kill()
            raise TimeoutError(f"baton {args[0]} not ready after {timeout_s} s: {log.read_text()}")
        time.sleep(0.02)
    return process, ready_file.read_text().strip().splitlines()[0]


def stop_program(process: subprocess.Popen[bytes]) -> None:
    """SIGTERM, then SIGKILL if it does not exit within 5 s."""
    process.terminate()
    try:
        process.wait(5)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait(5)


async def connect_as_master(
    stub: drone_pb2_grpc.DroneAsyncStub,
    controller_id: int,
    holds_reqnr: int = 0,
    given_up_epoch: int = 0,
) -> tuple[drone_pb2.Connected, list[drone_pb2.RetainedReply]]:
    """A Connect as ``controller_id``: its Connected event and the retained replies that
    follow it in batches, up to ``Connected.retained_through``; the stream is then closed."""
    call = stub.Connect(
        drone_pb2.ConnectRequest(
            controller_id=controller_id, holds_reqnr=holds_reqnr, given_up_epoch=given_up_epoch
        )
    )
    try:
        connected = (await next_message(call)).connected
        replies: list[drone_pb2.RetainedReply] = []
        through = connected.retained_through
        while through and (not replies or replies[-1].reqnr < through):
            replies.extend((await next_message(call)).retained.replies)
        return connected, replies
    finally:
        call.cancel()
