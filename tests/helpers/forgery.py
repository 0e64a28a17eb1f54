"""A stolen station's frames: log messages sent on a LogRing stream from a valid
controller certificate, as issue 33's attacker does (forged, altered, replayed)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import grpc

from baton.authenticity import needs_drone_signature
from baton.controller.history import read_log
from baton.controller.ring import frames
from baton.rpc.channels import aio_channel
from baton.rpc.tls import DRONE, Identity, Tls
from baton.v1 import drone_pb2, drone_pb2_grpc, ring_pb2, ring_pb2_grpc


def signed_message(log: Path) -> ring_pb2.LogMessage | None:
    """The newest message of a controller's log file with a reply the drone signed."""
    for message in reversed(read_log(log)):
        if any(needs_drone_signature(e) and e.drone_signature for e in message.entries):
            return message
    return None


def copy(message: ring_pb2.LogMessage) -> ring_pb2.LogMessage:
    copied = ring_pb2.LogMessage()
    copied.CopyFrom(message)
    return copied


async def send(
    address: str,
    station: Tls,
    receiver: int,
    message: ring_pb2.LogMessage,
    renumber: bool,
    seal: Callable[[ring_pb2.LogMessage], object] | None = None,
) -> None:
    """Sends ``message`` on a LogRing stream from ``station``'s certificate (numbered
    after what the receiver's hello says it holds if ``renumber``, then ``seal``ed) and
    waits for its acknowledgement: a refused message is acknowledged too (dropped, not
    asked again)."""
    async with aio_channel(address, station, Identity.controller(receiver)) as channel:
        call = ring_pb2_grpc.ControllerRingStub(channel).LogRing()
        hello = await call.read()
        assert isinstance(hello, ring_pb2.LogAck) and hello.hello
        if renumber:
            message.lognr = hello.lognr + 1
        if seal is not None:
            seal(message)
        for frame in frames(message, station.identity.number or 0):
            await call.write(frame)
        while True:
            ack = await call.read()
            assert isinstance(ack, ring_pb2.LogAck), ack
            if ack.lognr == message.lognr:
                break
        await call.done_writing()


async def say(
    address: str,
    station: Tls,
    receiver: int,
    words: Callable[[ring_pb2.LogAck], list[ring_pb2.LogFrame]],
) -> None:
    """Writes the sync frames ``words`` makes from the receiver's hello on a LogRing stream
    from ``station``'s certificate, in order, and ends the stream once the receiver has
    read them all (it ends its side then; a sync frame is not acknowledged)."""
    async with aio_channel(address, station, Identity.controller(receiver)) as channel:
        call = ring_pb2_grpc.ControllerRingStub(channel).LogRing()
        hello = await call.read()
        assert isinstance(hello, ring_pb2.LogAck) and hello.hello
        for frame in words(hello):
            frame.sync, frame.from_id = True, station.identity.number or 0
            await call.write(frame)
        await call.done_writing()
        while await call.read() is not grpc.aio.EOF:
            pass


async def operator_hands_over(drone_address: str, tls: Tls, new_master: int) -> None:
    """An operator asks the drone to make ``new_master`` master (``Drone.Handover``), as
    after a forgery: the controller that was lied to takes the role."""
    async with aio_channel(drone_address, tls, DRONE) as channel:
        moved = await drone_pb2_grpc.DroneStub(channel).Handover(
            drone_pb2.HandoverRequest(new_master=new_master)
        )
    assert moved.new_master == new_master, moved
