"""Measures a running drone service: T_conn, Invoke round trips, picture round trips.

    python -m baton.drone.measure --address HOST:PORT [--controller ID] [--calls 1000]

The measuring controller becomes the master (through the Handover RPC if
needed) and continues from the drone's last reqnr; the drone's own counters
and audit then include these calls. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import time
from pathlib import Path

from baton.controller.drone_link import InvokeCalls
from baton.logs import get_logger
from baton.rpc.channels import aio_channel
from baton.rpc.methods import path
from baton.rpc.streams import read_message
from baton.rpc.tls import DRONE, OPERATOR, Identity, Tls
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2, drone_pb2_grpc

GET_POSITION = path("Mobility.GetPosition")
TAKE_PICTURE = path("Camera.TakePicture")


def percentile(samples: list[float], q: float) -> float:
    """The q-th percentile (nearest rank) of ``samples``."""
    ordered = sorted(samples)
    return ordered[min(len(ordered) - 1, max(0, round(q / 100 * len(ordered)) - 1))]


def summary_ms(samples: list[float]) -> dict[str, float]:
    """p50 / p99 / mean / max of durations in seconds, as milliseconds."""
    return {
        "n": len(samples),
        "p50_ms": round(percentile(samples, 50) * 1e3, 3),
        "p99_ms": round(percentile(samples, 99) * 1e3, 3),
        "mean_ms": round(statistics.fmean(samples) * 1e3, 3),
        "max_ms": round(max(samples) * 1e3, 3),
    }


class MasterCalls:
    """Drone calls as the drone's master, numbered on from its last reqnr: what a
    program calling the drone directly would send (the benchmarks' baseline)."""

    def __init__(
        self, stub: drone_pb2_grpc.DroneAsyncStub, controller: int, epoch: int, reqnr: int
    ) -> None:
        self.stub = stub
        self.controller = controller
        self.epoch = epoch
        self.reqnr = reqnr
        self._stream: InvokeCalls | None = None

    @classmethod
    async def become_master(
        cls,
        stub: drone_pb2_grpc.DroneAsyncStub,
        address: str,
        controller: int,
        certs: Path | None,
    ) -> MasterCalls:
        """As ``controller`` over ``stub``'s channel to the drone at ``address``: made
        master first by an operator's Handover (with the operator's certificate in
        ``certs``) if it is not."""
        status = await stub.GetStatus(
            drone_pb2.GetDroneStatusRequest(), wait_for_ready=True, timeout=30
        )
        epoch = status.epoch
        if status.master != controller:
            operator = None if certs is None else Tls.load(certs, OPERATOR)
            async with aio_channel(address, operator, DRONE) as as_operator:
                handover = drone_pb2.HandoverRequest(new_master=controller)
                epoch = (await drone_pb2_grpc.DroneStub(as_operator).Handover(handover)).epoch
        return cls(stub, controller, epoch, status.last_reqnr)

    async def invoke(
        self,
        method: str = GET_POSITION,
        payload: bytes = b"",
        via: drone_pb2_grpc.DroneAsyncStub | None = None,
    ) -> drone_pb2.InvokeReply:
        """The next request, over ``via`` (a relay) or straight to the drone."""
        self.reqnr += 1
        request = drone_pb2.InvokeRequest(
            controller_id=self.controller,
            reqnr=self.reqnr,
            method=method,
            payload=payload,
            epoch=self.epoch,
        )
        reply: drone_pb2.InvokeReply = await (via or self.stub).Invoke(
            request, wait_for_ready=True, timeout=30
        )
        return reply

    async def timed(self, via: drone_pb2_grpc.DroneAsyncStub | None = None) -> float:
        """One GetPosition's round trip, in seconds."""
        start = time.perf_counter()
        await self.invoke(via=via)
        return time.perf_counter() - start

    async def timed_on_stream(self) -> float:
        """One GetPosition's round trip as a message on the kept InvokeStream (the
        controller's own way: ``drone_link.InvokeCalls``), in seconds."""
        if self._stream is None:
            self._stream = InvokeCalls(self.stub, get_logger("bench"))
        self.reqnr += 1
        request = drone_pb2.InvokeRequest(
            controller_id=self.controller, reqnr=self.reqnr, method=GET_POSITION, epoch=self.epoch
        )
        start = time.perf_counter()
        await self._stream.invoke(request, 30)
        return time.perf_counter() - start

    async def close(self) -> None:
        """Ends the stream of ``timed_on_stream``, if it was opened."""
        if self._stream is not None:
            await self._stream.close(grace=5)


async def measure(
    address: str,
    controller: int,
    count: int,
    pictures: int,
    connects: int,
    certs: Path | None = None,
) -> dict:
    """Runs the three measurements against the drone at ``address``: as the
    controller and (for the handover) an operator, with their certificates in
    ``certs``, or on an insecure port."""
    me = Identity.controller(controller)
    tls = None if certs is None else Tls.load(certs, me)
    channel = aio_channel(address, tls, DRONE)
    stub = drone_pb2_grpc.DroneStub(channel)
    calls = await MasterCalls.become_master(stub, address, controller, certs)

    async def connect(connect_stub: drone_pb2_grpc.DroneAsyncStub) -> float:
        start = time.perf_counter()
        stream = connect_stub.Connect(drone_pb2.ConnectRequest(controller_id=controller))
        event = await read_message(stream)
        elapsed = time.perf_counter() - start
        assert event is not None and event.HasField("connected"), event
        stream.cancel()
        return elapsed

    # T_conn as a controller that becomes ACTIVE sees it: a new channel (TCP
    # and HTTP/2 set-up) until the first event; and on an open channel.
    t_conn_new, t_conn_open = [], []
    for _ in range(connects):
        fresh = aio_channel(address, tls, DRONE)
        t_conn_new.append(await connect(drone_pb2_grpc.DroneStub(fresh)))
        await fresh.close()
        t_conn_open.append(await connect(stub))

    for _ in range(20):  # warm up the channel and the drone's telemetry path
        await calls.invoke()
    position = [await calls.timed() for _ in range(count)]

    picture, picture_bytes = [], 0
    for _ in range(pictures):
        start = time.perf_counter()
        reply = await calls.invoke(TAKE_PICTURE)
        picture.append(time.perf_counter() - start)
        picture_bytes = len(api.TakePictureReply.FromString(reply.payload).image)
    await channel.close()
    return {
        "address": address,
        "tls": tls is not None,
        "t_conn_new_channel": summary_ms(t_conn_new),
        "t_conn_open_channel": summary_ms(t_conn_open),
        "invoke_get_position": summary_ms(position) if position else None,
        "invoke_take_picture": {**summary_ms(picture), "image_bytes": picture_bytes},
    }


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m baton.drone.measure``."""
    parser = argparse.ArgumentParser(prog="python -m baton.drone.measure", description=__doc__)
    parser.add_argument("--address", required=True, help="HOST:PORT of a running drone service")
    parser.add_argument("--controller", type=int, default=0, help="controller id to measure as")
    parser.add_argument("--calls", type=int, default=1000, help="GetPosition calls (default 1000)")
    parser.add_argument("--pictures", type=int, default=20, help="TakePicture calls (default 20)")
    parser.add_argument("--connects", type=int, default=20, help="Connect set-ups (default 20)")
    parser.add_argument(
        "--certs",
        type=Path,
        help="folder with ca.crt and the controller's and operator's certificates "
        "(baton certs init); without it, the drone's port must be insecure",
    )
    args = parser.parse_args(argv)
    result = asyncio.run(
        measure(args.address, args.controller, args.calls, args.pictures, args.connects, args.certs)
    )
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
