"""LogRing streams over real gRPC sockets: framing, large logs, a restarting successor."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import grpc
import pytest

from baton.controller.history import LogHistory
from baton.controller.link_core import SyncWord
from baton.controller.receiver_core import Reassembler
from baton.controller.ring import (
    FRAME_BYTES,
    LogRingCall,
    PeerLink,
    RingReceiver,
    frames,
)
from baton.logs import get_logger
from baton.rpc.server import BatonServer, Servicer, servicer
from baton.rpc.streams import next_message
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
        self.words: list[tuple[int, ...]] = []  # the sync frames' master words
        self.receiver = RingReceiver(1, self.lognr, self.deliver, LOG, synced=self.synced)

    async def synced(self, from_id: int, word: SyncWord) -> None:
        self.syncs.append((from_id, word.holds, word.holds_epoch))
        self.words.append((word.master_epoch, word.master_lognr))

    def lognr(self) -> int:
        return max((m.lognr for m in self.messages), default=0)

    async def deliver(self, message: ring_pb2.LogMessage, relayed_by: int = 0) -> None:
        if message.lognr not in {m.lognr for m in self.messages}:
            self.messages.append(message)
        self.arrived.set()

    async def LogRing(self, request_iterator, context):  # type: ignore[no-untyped-def, override]
        await self.receiver.serve(context)


def _ring(impl: ring_pb2_grpc.ControllerRingServicer) -> Servicer:
    return servicer(
        "baton.v1.ControllerRing", ring_pb2_grpc.add_ControllerRingServicer_to_server, impl
    )


async def start_receiver(address: str) -> tuple[BatonServer, Receiver]:
    receiver = Receiver()  # type: ignore[abstract]
    server = BatonServer(address, [_ring(receiver)])
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


async def test_a_sync_frame_says_the_masters_word_and_again_when_it_changes(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """--policy nearest seed 48: the newest ACTIVE master's word (epoch, log number held)
    rides on every sync frame, and a changed word is written once the link is woken
    (the node wakes it when it dropped queued messages on such a word)."""
    server, receiver = await start_receiver(f"127.0.0.1:{free_port()}")
    history = LogHistory(tmp_path / "history.sqlite")
    link = PeerLink(0, 1, server.address, LOG, history)
    word = (15, 9)
    link.master_word = lambda: word
    try:
        history.add(big_message(1, 10))
        link.send(big_message(1, 10))
        await wait_for(lambda: link.unacked == 0 and receiver.words)
        assert receiver.words == [(15, 9)]
        word = (16, 9)
        link.holds_changed()
        await wait_for(lambda: len(receiver.words) == 2)
        assert receiver.words[-1] == (16, 9) and receiver.syncs[-1] == (0, 1, 0)
    finally:
        await link.stop()
        await server.stop(0)
        history.close()


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


class Certified(Receiver):
    """A receiver whose streams come from controller 0, as a certificate would say."""

    async def LogRing(self, request_iterator, context):  # type: ignore[no-untyped-def, override]
        await self.receiver.serve(context, sender=0)


async def refusal_of(address: str, sent: list[ring_pb2.LogFrame]) -> grpc.aio.AioRpcError:
    """How a LogRing stream that writes ``sent`` ends (the receiver's refusal)."""
    async with grpc.aio.insecure_channel(address) as channel:
        call = ring_pb2_grpc.ControllerRingStub(channel).LogRing()
        assert (await next_message(call)).hello
        for frame in sent:
            await call.write(frame)
        with pytest.raises(grpc.aio.AioRpcError) as ended:
            await next_message(call)
        return ended.value


async def test_the_receivers_refusals_end_the_stream_with_their_status_and_words() -> None:
    """The driver carries out ``ReceiverCore``'s refusals as they are: the caller reads
    the status and the text that names what was wrong."""
    receiver = Certified()  # type: ignore[abstract]
    server = BatonServer("127.0.0.1:0", [_ring(receiver)])
    await server.start()
    try:
        (foreign,) = frames(big_message(1, 10), from_id=2)
        denied = await refusal_of(server.address, [foreign])
        assert denied.code() is grpc.StatusCode.PERMISSION_DENIED
        assert denied.details() == (
            "LogRing: controller 0's certificate sent a frame from_id 2; a controller sends "
            "its own frames only"
        )
        first, _, third = frames(big_message(1, 2 * FRAME_BYTES), from_id=0)
        unordered = await refusal_of(server.address, [first, third])
        assert unordered.code() is grpc.StatusCode.INVALID_ARGUMENT
        assert unordered.details() == (
            f"frame of log message 1 at offset {2 * FRAME_BYTES} does not follow message 1 "
            f"at offset {FRAME_BYTES}"
        )
        assert receiver.messages == []
    finally:
        await server.stop(0)


# -- cut-through (docs/design.md, "The ring's forwarding") ---------------------------


class Relaying(ring_pb2_grpc.ControllerRingServicer):
    """A middle controller B: forwards to C what ``forwards`` says, cut-through, as the
    node does (``ControllerNode.relay_for``, ``on_log`` -> ``PeerLink.send``). Its
    handling of a whole message waits on ``gate``."""

    def __init__(self, successor: str, forwards) -> None:  # type: ignore[no-untyped-def]
        self.link = PeerLink(1, 2, successor, LOG)
        self.forwards = forwards
        self.gate = asyncio.Event()
        self.gate.set()
        self.handling = asyncio.Event()
        self.handled: list[int] = []
        self.receiver = RingReceiver(
            1, lambda: max(self.handled, default=0), self.deliver, LOG, relay=self.relay
        )

    def relay(self, head: ring_pb2.LogMessage, total: int):  # type: ignore[no-untyped-def]
        return self.link.relay(head.lognr, total) if self.forwards(head) else None

    async def deliver(self, message: ring_pb2.LogMessage, relayed_by: int = 0) -> None:
        self.handling.set()
        await self.gate.wait()
        if message.lognr in self.handled:
            return
        self.handled.append(message.lognr)
        if self.forwards(message, whole=True):
            self.link.send(message)

    async def LogRing(self, request_iterator, context):  # type: ignore[no-untyped-def, override]
        await self.receiver.serve(context)


async def start_chain(forwards):  # type: ignore[no-untyped-def]
    """A -> B -> C: returns C's server and receiver, B's server and servicer."""
    c_server, c = await start_receiver("127.0.0.1:0")
    b = Relaying(c_server.address, forwards)  # type: ignore[abstract]
    b_server = BatonServer("127.0.0.1:0", [_ring(b)])
    await b_server.start()
    return c_server, c, b_server, b


def test_the_first_frame_says_the_head_and_the_rest_only_bytes() -> None:
    message = big_message(5, 3 * FRAME_BYTES)
    message.epoch, message.after_reqnr = 4, 9
    parts = frames(message, from_id=0)
    head = parts[0].head
    assert (head.lognr, head.epoch, head.after_reqnr, len(head.entries)) == (5, 4, 9, 0)
    assert not any(part.HasField("head") for part in parts[1:])


async def test_frames_go_on_before_the_message_is_whole_and_the_last_one_after() -> None:
    c_server, c, b_server, b = await start_chain(lambda m, whole=False: True)
    a = PeerLink(0, 1, b_server.address, LOG)
    try:
        b.gate.clear()  # B holds the whole message unhandled
        message = big_message(1, 4 * 2**20)
        total = message.ByteSize()
        a.send(message)
        await b.handling.wait()
        # Everything but the last frame went on to C while B had not handled it yet.
        last = total - (total - 1) // FRAME_BYTES * FRAME_BYTES
        await wait_for(lambda: b.link.counters.sent_bytes == total - last)
        assert c.messages == []
        b.gate.set()
        await wait_for(lambda: c.messages and b.link.unacked == 0)
        assert c.messages == [message]
        assert (b.link.counters.relayed_messages, b.link.counters.relays_aborted) == (1, 0)
    finally:
        for link in (a, b.link):
            await link.stop()
        await b_server.stop(0)
        await c_server.stop(0)


async def test_a_relayed_message_not_forwarded_after_all_is_dropped_downstream() -> None:
    """B starts passing message 1 on (its head says forward), then does not forward it
    whole (e.g. the ring's state changed meanwhile): C drops what it got and takes the
    next message intact."""
    c_server, c, b_server, b = await start_chain(
        lambda m, whole=False: not (whole and m.lognr == 1)
    )
    a = PeerLink(0, 1, b_server.address, LOG)
    try:
        first, second = big_message(1, 200_000), big_message(2, 50_000)
        a.send(first)
        a.send(second)
        await wait_for(lambda: c.messages and b.link.unacked == 0)
        assert c.messages == [second]
        assert (b.link.counters.relayed_messages, b.link.counters.relays_aborted) == (1, 1)
    finally:
        for link in (a, b.link):
            await link.stop()
        await b_server.stop(0)
        await c_server.stop(0)


async def test_a_stream_broken_mid_message_loses_and_duplicates_nothing() -> None:
    """A's stream to B breaks half-way through a cut-through message: B's relay is
    given up (C drops its part), A re-sends on a new stream, C gets it once, whole."""
    c_server, c, b_server, b = await start_chain(lambda m, whole=False: True)
    message = big_message(1, 1 << 20)
    parts = frames(message, from_id=0)
    channel = grpc.aio.insecure_channel(b_server.address)
    a = PeerLink(0, 1, b_server.address, LOG)
    try:
        call = ring_pb2_grpc.ControllerRingStub(channel).LogRing()
        hello = await next_message(call)
        assert hello.hello
        for part in parts[: len(parts) // 2]:
            await call.write(part)
        await wait_for(lambda: b.link.counters.sent_bytes >= FRAME_BYTES)
        call.cancel()  # the stream breaks part-way
        await wait_for(lambda: b.link.counters.relays_aborted == 1)
        a.send(message)  # the sender's reconnect re-sends what was not acknowledged
        await wait_for(lambda: c.messages and b.link.unacked == 0 and a.unacked == 0)
        assert c.messages == [message] and b.handled == [1]
        assert b.link.counters.relayed_messages == 1
    finally:
        for link in (a, b.link):
            await link.stop()
        await channel.close()
        await b_server.stop(0)
        await c_server.stop(0)


class Holding(Receiver):
    """A receiver that says it holds message 1 already, ``held_answers`` times."""

    def __init__(self, held_answers: int) -> None:
        super().__init__()
        self.asked = 0
        self.held_answers = held_answers
        self.receiver = RingReceiver(1, self.lognr, self.deliver, LOG, held=self.held)

    def held(self, head: ring_pb2.LogMessage) -> bool:
        if head.lognr != 1:
            return False
        self.asked += 1
        return self.asked <= self.held_answers


async def start_holding(held_answers: int) -> tuple[BatonServer, Holding]:
    receiver = Holding(held_answers)  # type: ignore[abstract]
    server = BatonServer("127.0.0.1:0", [_ring(receiver)])
    await server.start()
    return server, receiver


async def test_a_message_held_already_is_acknowledged_without_being_parsed() -> None:
    """A handover's target gets the old master's message straight and round the ring;
    the copy whose other came whole meanwhile is counted, acknowledged, not parsed."""
    server, receiver = await start_holding(held_answers=1_000)
    link = PeerLink(0, 1, server.address, LOG)
    try:
        link.send(big_message(1, 4 * FRAME_BYTES))
        link.send(big_message(2, 10))
        await wait_for(lambda: link.unacked == 0 and len(receiver.messages) == 1)
        assert [m.lognr for m in receiver.messages] == [2]  # 1 acknowledged, not delivered
        assert receiver.asked >= 2  # asked mid-way, and again at its last frame
    finally:
        await link.stop()
        await server.stop(0)


async def test_a_message_let_go_as_held_and_no_longer_held_is_sent_again() -> None:
    """The receiver rejoined with nothing while it let a message's frames go: it does not
    acknowledge it, its stream ends, and the sender's re-send is delivered whole."""
    server, receiver = await start_holding(held_answers=1)
    link = PeerLink(0, 1, server.address, LOG)
    try:
        message = big_message(1, 4 * FRAME_BYTES)
        link.send(message)
        await wait_for(lambda: link.unacked == 0 and receiver.messages, timeout=30)
        assert receiver.messages == [message]
        assert link.counters.connects >= 2
    finally:
        await link.stop()
        await server.stop(0)


class EndedBeforeFrame:
    """A real LogRing call whose receiver ends the RPC (``end``, once of all the calls
    it wraps) just before the first frame of message ``lognr`` is written: the write
    meets a finished call, as when a stream ends between a frame taken off a relay and
    its write."""

    def __init__(self, call: LogRingCall, lognr: int, end: list[Callable[[], None]]) -> None:
        self._call = call
        self._lognr = lognr
        self._end = end

    def __getattr__(self, name: str) -> Any:
        return getattr(self._call, name)

    async def write(self, frame: ring_pb2.LogFrame) -> None:
        if self._end and frame.lognr == self._lognr and frame.offset == 0 and not frame.sync:
            self._end.pop()()
            await self._call.code()  # the RPC finished: its status arrived
        await self._call.write(frame)


async def test_a_relay_whose_frame_meets_a_finished_stream_goes_whole_on_the_next(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """B passes message 2 on to its successor C cut-through; C ends the stream (it
    rejoined with nothing: ``drop_streams``) as B takes the message's one frame off the
    relay, and grpc refuses the write ('RPC already finished'). The frame is gone with
    the stream: the relay is given up, and the next stream gives C the message whole.
    The stream's end is a stream down (a warning), not an unexpected error."""
    caplog.set_level(logging.INFO, logger="baton.test")
    server, c = await start_receiver("127.0.0.1:0")
    stub = ring_pb2_grpc.ControllerRingStub
    end = [c.receiver.drop_streams]

    class Stub:
        def __init__(self, channel: grpc.aio.Channel) -> None:
            self._stub = stub(channel)

        def LogRing(self, *args: Any, **kwargs: Any) -> EndedBeforeFrame:
            return EndedBeforeFrame(self._stub.LogRing(*args, **kwargs), 2, end)

    monkeypatch.setattr(ring_pb2_grpc, "ControllerRingStub", Stub)
    history = LogHistory(tmp_path / "history.sqlite")
    link = PeerLink(1, 2, server.address, LOG, history)
    try:
        first, second = big_message(1, 10), big_message(2, 10)
        history.add(first)
        link.send(first)
        await wait_for(lambda: link.unacked == 0 and c.messages)
        (frame,) = frames(second, from_id=0)
        relay = link.relay(2, frame.total_bytes)
        assert relay is not None
        relay.add(frame)
        history.add(second)
        link.send(second)  # forwarded whole: the relay's last frame may go
        await wait_for(lambda: link.unacked == 0 and len(c.messages) == 2)
        assert [m.lognr for m in c.messages] == [1, 2]
        assert (link.counters.relayed_messages, link.counters.relays_aborted) == (0, 1)
        assert link.counters.connects == 2 and not end
        said = [(r.levelname, r.getMessage()) for r in caplog.records if r.name == "baton.test"]
        assert ("WARNING", "ring stream down; reconnecting") in said
        assert not [line for line in said if line[0] == "ERROR"]
    finally:
        await link.stop()
        await server.stop(0)
        history.close()
