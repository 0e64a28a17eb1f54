"""LogRing streams over real gRPC sockets: framing, large logs, a restarting successor."""

from __future__ import annotations

import asyncio

import pytest

from baton.controller.history import LogHistory
from baton.controller.ring import FRAME_BYTES, PeerLink, Reassembler, RingReceiver, frames
from baton.logs import get_logger
from baton.rpc.server import BatonServer
from baton.testbed.local import free_port
from baton.v1 import ring_pb2, ring_pb2_grpc

LOG = get_logger("test")


def big_message(lognr: int, size: int) -> ring_pb2.LogMessage:
    return ring_pb2.LogMessage(
        lognr=lognr,
        origin=0,
        entries=[
            ring_pb2.LogEntry(reqnr=lognr, method="/baton.v1.Camera/TakePicture", reply=b"p" * size)
        ],
    )


def test_frames_reassemble_to_the_same_message() -> None:
    message = big_message(7, 3 * FRAME_BYTES + 5)
    parts = frames(message, from_id=0)
    assert len(parts) == 4 and all(len(f.data) <= FRAME_BYTES for f in parts)
    r = Reassembler()
    results = [r.add(f) for f in parts]
    assert results[:-1] == [None] * 3 and results[-1] == message


def test_empty_message_is_one_frame() -> None:
    message = ring_pb2.LogMessage()
    (frame,) = frames(message, from_id=0)
    assert Reassembler().add(frame) == message


def test_frame_out_of_order_is_refused() -> None:
    parts = frames(big_message(1, 2 * FRAME_BYTES), from_id=0)
    r = Reassembler()
    r.add(parts[0])
    with pytest.raises(ValueError, match="does not follow"):
        r.add(parts[2])


class Receiver(ring_pb2_grpc.ControllerRingServicer):
    def __init__(self) -> None:
        self.messages: list[ring_pb2.LogMessage] = []
        self.arrived = asyncio.Event()
        self.syncs: list[tuple[int, int, int]] = []
        self.receiver = RingReceiver(1, self.lognr, self.deliver, LOG, synced=self.synced)

    async def synced(self, from_id: int, holds_lognr: int, holds_epoch: int) -> None:
        self.syncs.append((from_id, holds_lognr, holds_epoch))

    def lognr(self) -> int:
        return max((m.lognr for m in self.messages), default=0)

    async def deliver(self, message: ring_pb2.LogMessage) -> None:
        if message.lognr not in {m.lognr for m in self.messages}:
            self.messages.append(message)
        self.arrived.set()

    async def LogRing(self, request_iterator, context):  # type: ignore[no-untyped-def]
        await self.receiver.serve(context)


async def start_receiver(address: str) -> tuple[BatonServer, Receiver]:
    receiver = Receiver()
    server = BatonServer(address, ["baton.v1.ControllerRing"])
    ring_pb2_grpc.add_ControllerRingServicer_to_server(receiver, server.server)
    await server.start()
    return server, receiver


async def wait_for(predicate, timeout: float = 20.0) -> None:  # type: ignore[no-untyped-def]
    async with asyncio.timeout(timeout):
        while not predicate():
            await asyncio.sleep(0.01)


async def test_a_64_mb_log_message_passes_the_ring() -> None:
    server, receiver = await start_receiver("127.0.0.1:0")
    link = PeerLink(0, 1, server.address, LOG)
    try:
        message = big_message(1, 64 * 2**20)
        link.send(message)
        await wait_for(lambda: link.unacked == 0 and receiver.messages, timeout=60)
        assert receiver.messages[0].ByteSize() == message.ByteSize()
        assert receiver.messages[0] == message
    finally:
        await link.stop()
        await server.stop(0)


async def test_successor_restart_loses_nothing(tmp_path) -> None:  # type: ignore[no-untyped-def]
    address = f"127.0.0.1:{free_port()}"
    server, first = await start_receiver(address)
    history = LogHistory(tmp_path / "history.sqlite")
    link = PeerLink(0, 1, address, LOG, history)

    def send(message: ring_pb2.LogMessage) -> None:
        history.add(message)  # as the node does with every message it sends or receives
        link.send(message)

    try:
        send(big_message(1, 10))
        await wait_for(lambda: link.unacked == 0)
        # The stream's first frame: what the sender holds, and its top message's epoch.
        assert first.syncs == [(0, 1, 0)]
        # A message the successor created itself (it came round to us): never sent
        # to it while it lives, but it is in our history.
        history.add(ring_pb2.LogMessage(lognr=2, origin=1, handover=True))
        await server.stop(0)
        # Sent while the successor is down: kept until it is back.
        send(big_message(3, 10))
        last = big_message(4, 10)
        last.epoch = 3
        send(last)
        await wait_for(lambda: not link.stream_up)
        assert link.unacked >= 2
        server, restarted = await start_receiver(address)
        await wait_for(lambda: link.unacked == 0 and len(restarted.messages) == 4)
        # The restarted successor held nothing (hello lognr 0): it got the whole
        # history, its own old message included, as a normal (not handover) one.
        assert [m.lognr for m in restarted.messages] == [1, 2, 3, 4]
        assert restarted.messages[1].origin == 1 and not restarted.messages[1].handover
        assert restarted.syncs == [(0, 4, 3)]
        assert link.counters.connects == 2
    finally:
        await link.stop()
        await server.stop(0)
        history.close()


async def test_a_log_number_sent_again_is_written_again_and_acknowledged() -> None:
    """A former master given the role back by takeover sends its handover message on,
    maybe on the stream that carried it (protocol.py ``_resend_handed``): it was kept
    unacknowledged for good when the stream had written that number already."""
    server, receiver = await start_receiver("127.0.0.1:0")
    link = PeerLink(0, 1, server.address, LOG)
    try:
        handover = ring_pb2.LogMessage(lognr=1, origin=1, handover=True)
        link.send(handover)
        await wait_for(lambda: link.unacked == 0 and receiver.messages)
        arrivals = link.counters.acked
        link.send(ring_pb2.LogMessage(lognr=1, origin=1))
        await wait_for(lambda: link.unacked == 0 and link.counters.acked > arrivals, timeout=5)
        assert link.counters.connects == 1
    finally:
        await link.stop()
        await server.stop(0)


def test_a_frame_claiming_more_than_the_limit_is_refused_before_buffering() -> None:
    """Issue 9, defect 8: the reassembler accepted a frame that claimed any total size."""
    r = Reassembler(max_bytes=1000)
    claim = ring_pb2.LogFrame(lognr=3, total_bytes=2**40, offset=0, data=b"x")
    with pytest.raises(ValueError, match="claims 1099511627776 bytes, above max_log_message"):
        r.add(claim)
    message = big_message(4, 900)
    assert r.add(frames(message, from_id=0)[0]) == message  # within the limit: as before


async def test_a_settled_handover_message_is_sent_again_without_its_flag() -> None:
    """Simulation finding F9: a handover message whose acknowledgement was lost went to a
    receiver that restarted after handing the role on; once the ring went past it, the
    old master's link writes it without the flag (``settle_handovers``)."""
    address = f"127.0.0.1:{free_port()}"
    link = PeerLink(0, 1, address, LOG)
    server = None
    try:
        link.send(ring_pb2.LogMessage(lognr=1, origin=1, handover=True))
        link.send(ring_pb2.LogMessage(lognr=2, origin=0))
        assert link.settle_handovers(lambda lognr: False) == []
        (settled,) = link.settle_handovers(lambda lognr: lognr == 1)
        assert settled.lognr == 1 and settled.handover  # as it was: for the history
        assert link.settle_handovers(lambda lognr: True) == []  # once
        server, receiver = await start_receiver(address)
        await wait_for(lambda: link.unacked == 0 and len(receiver.messages) == 2)
        assert [(m.lognr, m.handover) for m in receiver.messages] == [(1, False), (2, False)]
    finally:
        await link.stop()
        if server is not None:
            await server.stop(0)
