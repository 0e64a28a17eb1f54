"""The drone service and a vehicle as real processes, and a controller as the drone sees it."""

from __future__ import annotations

import subprocess
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import grpc
from drone_harness import start_program, stop_program
from google.protobuf.message import Message

from baton.certs.make import init
from baton.rpc.channels import sync_channel
from baton.rpc.tls import DRONE, OPERATOR, Identity, Tls
from baton.v1 import drone_pb2, drone_pb2_grpc

M = TypeVar("M", bound=Message)


EARTH_RADIUS_M = 6_371_000.0


SPEEDUP = "10"


@dataclass
class DroneBed:
    """A running sim vehicle and drone service; ``stub`` calls it as the operator."""

    address: str
    certs: Path
    processes: list[subprocess.Popen[bytes]] = field(default_factory=list)
    channels: dict[Identity, grpc.Channel] = field(default_factory=dict)
    vehicle_url: str = ""

    def as_(self, identity: Identity) -> drone_pb2_grpc.DroneStub:
        """A stub that calls with ``identity``'s certificate."""
        if identity not in self.channels:
            tls = Tls.load(self.certs, identity)
            self.channels[identity] = sync_channel(self.address, tls, DRONE)
        return drone_pb2_grpc.DroneStub(self.channels[identity])

    def as_controller(self, cid: int) -> drone_pb2_grpc.DroneStub:
        return self.as_(Identity.controller(cid))

    @property
    def stub(self) -> drone_pb2_grpc.DroneStub:
        return self.as_(OPERATOR)

    def status(self, audit: bool = False) -> drone_pb2.DroneStatus:
        return self.stub.GetStatus(drone_pb2.GetDroneStatusRequest(include_audit=audit), timeout=5)

    def wait_until(
        self, what: str, check: Callable[[drone_pb2.DroneStatus], bool], timeout_s: float = 60
    ) -> drone_pb2.DroneStatus:
        deadline = time.monotonic() + timeout_s
        while True:
            status = self.status()
            if check(status):
                return status
            if time.monotonic() > deadline:
                raise AssertionError(f"{what} not reached in {timeout_s} s; status: {status}")
            time.sleep(0.05)


@contextmanager
def drone_bed(
    tmp_path: Path,
    url: str | None,
    speedup: float,
    handovers: str = "# the master switches after the landing command\n7 1\n",
    *,
    vehicle_key: Path | None = None,
    drone_key: Path | None = None,
    ready: bool = True,
) -> Iterator[DroneBed]:
    """The drone service (and the sim vehicle, when ``url`` is None) as processes.

    ``vehicle_key`` and ``drone_key`` turn MAVLink signing on at either end;
    ``ready=False`` does not wait for the vehicle to be ready to arm.
    """
    script = tmp_path / "handovers.txt"
    script.write_text(handovers)
    certs = tmp_path / "certs"
    init(certs, [*(Identity.controller(cid) for cid in (0, 1, 2)), DRONE, OPERATOR])
    processes = []
    if url is None:  # the embedded sim vehicle
        sim, url = start_program(
            ["sim-vehicle", "--speedup", str(speedup), "--url-file", str(tmp_path / "url")]
            + ([f"--mavlink-key={vehicle_key}"] if vehicle_key else []),
            tmp_path / "url",
            tmp_path / "sim.log",
        )
        processes.append(sim)
    try:
        drone, address = start_program(
            [
                "drone",
                "--address=127.0.0.1:0",
                f"--address-file={tmp_path / 'address'}",
                f"--vehicle-url={url}",
                "--controllers=0,1,2",
                "--initial-master=0",
                f"--handover-file={script}",
                f"--speedup={speedup}",
                f"--certs={certs}",
                *([f"--mavlink-key={drone_key}"] if drone_key else []),
            ],
            tmp_path / "address",
            tmp_path / "drone.log",
        )
        processes.append(drone)
        bed = DroneBed(address, certs, processes, vehicle_url=url)
        # ArduPilot arms ~40 s (of its time) after boot: minutes at worst on a loaded box.
        if ready:
            bed.wait_until(
                "vehicle ready", lambda s: s.vehicle_connected and s.flight_state.ready, 120
            )
        yield bed
        for channel in bed.channels.values():
            channel.close()
    finally:
        for process in reversed(processes):
            stop_program(process)


class Controller:
    """A controller as the drone sees it: an id, its epoch and the next request number."""

    def __init__(self, bed: DroneBed, cid: int, reqnr: int = 1, epoch: int = 1) -> None:
        self.bed, self.cid, self.reqnr, self.epoch = bed, cid, reqnr, epoch

    def invoke(self, method: str, request: Message, reply_type: type[M]) -> tuple[M, bool]:
        reply = self.bed.as_controller(self.cid).Invoke(
            drone_pb2.InvokeRequest(
                controller_id=self.cid,
                reqnr=self.reqnr,
                method=method,
                payload=request.SerializeToString(),
                epoch=self.epoch,
            ),
            timeout=15,
        )
        assert reply.reqnr == self.reqnr
        self.reqnr += 1
        return reply_type.FromString(reply.payload), reply.duplicate
