"""Stations (``baton station``) and the drones of their missions as real processes."""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc

from baton.effects import read_effects
from baton.rpc.channels import aio_channel
from baton.rpc.mission import mission_metadata
from baton.rpc.tls import DRONE, OPERATOR, Identity, Tls
from baton.testbed.local import Snapshot
from baton.testbed.supervisor import Supervisor, baton_argv
from baton.v1 import drone_pb2, drone_pb2_grpc, ring_pb2, ring_pb2_grpc, station_pb2_grpc


@dataclass
class StationPart:
    """A running station: its id, its port, its state folder, and an operator's stub."""

    id: int
    address: str
    state_dir: Path
    channel: grpc.aio.Channel
    stub: station_pb2_grpc.StationAsyncStub

    async def status(self, mission_id: str) -> ring_pb2.ControllerStatus:
        """A hosted mission's ControllerStatus, asked on the station's port as any part
        asks it: ControllerRing.GetStatus naming the mission."""
        ring: ring_pb2_grpc.ControllerRingAsyncStub = ring_pb2_grpc.ControllerRingStub(self.channel)
        return await ring.GetStatus(
            ring_pb2.GetControllerStatusRequest(), metadata=mission_metadata(mission_id), timeout=5
        )


async def start_stations(
    supervisor: Supervisor, ids: Sequence[int], certs: Path
) -> dict[int, StationPart]:
    """``baton station`` processes with ids ``ids``, each on a free port, and an
    operator's channel to each."""
    workdir = supervisor.workdir
    parts = [
        (
            f"station-{sid}",
            baton_argv(
                "station",
                f"--id={sid}",
                "--address=127.0.0.1:0",
                f"--address-file={workdir / f'station-{sid}.address'}",
                f"--state-dir={workdir / f'station-{sid}'}",
                f"--certs={certs}",
            ),
            workdir / f"station-{sid}.address",
        )
        for sid in ids
    ]
    addresses = await supervisor.start_ready_together(parts)
    operator = Tls.load(certs, OPERATOR)
    stations = {}
    for sid, text in zip(ids, addresses, strict=True):
        address = text.splitlines()[0]
        channel = aio_channel(address, operator, Identity.controller(sid))
        stub = station_pb2_grpc.StationStub(channel)
        stations[sid] = StationPart(sid, address, workdir / f"station-{sid}", channel, stub)
    return stations


def mission_config(
    drone_address: str,
    stations: dict[int, StationPart],
    ring: Sequence[int],
    certs: Path,
    speedup: float = 20.0,
) -> dict[str, Any]:
    """A mission's configuration: its drone, and its ring's stations at their ports."""
    return {
        "drone": {"address": drone_address},
        "controllers": [{"id": sid, "address": stations[sid].address} for sid in ring],
        "ring": list(ring),
        "speedup": speedup,
        "flush_limit": 0,
        "tls": {"certs": str(certs)},
    }


@dataclass
class MissionDrone:
    """A mission's sim vehicle and drone service, and where they count side effects."""

    name: str
    address: str
    workdir: Path
    channel: grpc.aio.Channel
    stub: drone_pb2_grpc.DroneAsyncStub

    @property
    def vehicle_effects(self) -> Path:
        return self.workdir / "vehicle-effects.jsonl"

    @property
    def camera_effects(self) -> Path:
        return self.workdir / "camera-effects.jsonl"

    async def status(self, audit: bool = False) -> drone_pb2.DroneStatus:
        return await self.stub.GetStatus(
            drone_pb2.GetDroneStatusRequest(include_audit=audit), timeout=5
        )

    async def ready(self) -> bool:
        """Whether its vehicle is connected and ready to arm."""
        status = await self.status()
        return status.vehicle_connected and status.flight_state.ready

    async def served(self, reqnr: int) -> bool:
        """Whether it has served request ``reqnr``."""
        return (await self.status()).last_reqnr >= reqnr

    async def snapshot(self, controllers: dict[int, ring_pb2.ControllerStatus]) -> Snapshot:
        """The drone's status with its audit, its ring's statuses and the effects counted."""
        return Snapshot(
            await self.status(audit=True),
            controllers,
            read_effects(self.vehicle_effects),
            read_effects(self.camera_effects),
        )


async def start_mission_drone(
    supervisor: Supervisor,
    name: str,
    stations: dict[int, StationPart],
    ring: Sequence[int],
    handovers: Sequence[tuple[int, int]],
    certs: Path,
    speedup: float = 20.0,
) -> MissionDrone:
    """A sim vehicle and a drone service for a mission over ``ring`` (its first the
    master, then the scripted ``handovers``), ready to arm."""
    workdir = supervisor.workdir / name
    workdir.mkdir()
    url = await supervisor.start_ready(
        f"{name}-vehicle",
        baton_argv(
            "sim-vehicle",
            f"--speedup={speedup}",
            f"--url-file={workdir / 'vehicle.url'}",
            f"--effects-file={workdir / 'vehicle-effects.jsonl'}",
        ),
        workdir / "vehicle.url",
    )
    config = workdir / "drone.json"
    config.write_text(json.dumps(mission_config("127.0.0.1:0", stations, ring, certs, speedup)))
    script = workdir / "handovers.txt"
    script.write_text("".join(f"{after} {to}\n" for after, to in handovers))
    address = await supervisor.start_ready(
        f"{name}-drone",
        baton_argv(
            "drone",
            f"--config={config}",
            "--address=127.0.0.1:0",
            f"--address-file={workdir / 'drone.address'}",
            f"--vehicle-url={url.splitlines()[0]}",
            f"--handover-file={script}",
            f"--state={workdir / 'drone-state.sqlite'}",
            f"--camera-effects-file={workdir / 'camera-effects.jsonl'}",
        ),
        workdir / "drone.address",
    )
    address = address.splitlines()[0]
    channel = aio_channel(address, Tls.load(certs, OPERATOR), DRONE)
    return MissionDrone(name, address, workdir, channel, drone_pb2_grpc.DroneStub(channel))
