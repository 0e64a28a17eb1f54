"""The log ring: LogRing streams between controllers, of any message size.

A log message can be far larger than one gRPC message (64 MB and more), so it
travels as ``LogFrame`` slices of its serialized form (``FRAME_BYTES`` each)
and is acknowledged whole. Each destination has one ``PeerLink``: a stream
opened once and kept, re-opened with back-off when it breaks (the successor
restarted, a link dropped). On every new stream the receiver first says the
highest log number it has handled; the sender answers with a sync frame
saying the highest it holds, then re-sends what it sent and was not
acknowledged and, to its successor, every message of its history above the
receiver's number, whatever its origin (a restarted successor holds
nothing, not even the messages it once created). The receiver ignores what
it already has (``ControllerProtocol.on_log``), so nothing is lost and
nothing is handled twice.

Cut-through (docs/design.md, "The ring's forwarding"): a message's first frame
carries its head (the message without its entries), and a controller that
would forward it (``ControllerProtocol.forward_dest``) passes each frame on to
its successor as it arrives (a ``Relay``), all but the last, which goes only
once the whole message was handled and the protocol forwarded it; otherwise
the successor is told to drop it (an abort frame). So a successor gets whole
exactly the messages it would get from store-and-forward, in the same order,
one frame's time behind its predecessor instead of one message's.

Both ends here are drivers: a ``PeerLink`` carries out its ``LinkCore``
(``link_core.py``), and each stream a ``RingReceiver`` serves feeds its frames
to a ``ReceiverCore`` (``receiver_core.py``) and carries out the actions it
returns; what a stream refuses, delivers, acknowledges or passes on is decided
there.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Coroutine
from typing import Any, cast

import grpc
from google.protobuf.message import DecodeError

from baton.config import MAX_LOG_MESSAGE_DEFAULT
from baton.controller.history import LogHistory
from baton.controller.link_core import LinkCore, PeerCounters, RelayCore, SyncWord
from baton.controller.receiver_core import (
    AbortRelay,
    Ack,
    Arriving,
    Deliver,
    ReceiverCore,
    Refuse,
    RelayFrame,
    SettleRelay,
    StartRelay,
    Synced,
    WaitForRoom,
)
from baton.logs import BoundLogger
from baton.rpc.channels import aio_channel
from baton.rpc.mission import mission_metadata
from baton.rpc.streams import read_message, write_message
from baton.rpc.tls import Identity, Tls
from baton.v1 import ring_pb2, ring_pb2_grpc

# The default frame size (the testbed file's ring.frame_bytes): a frame costs
# 5 ms at 25 Mbit/s, the delay cut-through adds per hop (docs/design.md).
FRAME_BYTES = 16 << 10
# A relay holds at most this many frames not yet written on while its peer's
# stream writes it: the stream it comes on waits for room (``Relay.room``).
RELAY_WINDOW_FRAMES = 4

# A LogRing stream, as its sender holds it (Call) and as its receiver serves it (Context).
LogRingCall = grpc.aio.StreamStreamCall[ring_pb2.LogFrame, ring_pb2.LogAck]
LogRingContext = grpc.aio.ServicerContext[ring_pb2.LogFrame, ring_pb2.LogAck]


def head_of(message: ring_pb2.LogMessage) -> ring_pb2.LogMessage:
    """The message without its entries: what a first frame says of it."""
    head = ring_pb2.LogMessage()
    for field, value in message.ListFields():
        if field.name == "entries":
            continue
        if field.message_type is not None:  # the grant
            getattr(head, field.name).CopyFrom(value)
        else:
            setattr(head, field.name, value)
    return head


def frames(
    message: ring_pb2.LogMessage, from_id: int, frame_bytes: int = FRAME_BYTES
) -> list[ring_pb2.LogFrame]:
    """Slices a serialized log message into frames (at least one, even when empty);
    the first carries the message's head."""
    data = message.SerializeToString()
    total = len(data)
    out = [
        ring_pb2.LogFrame(
            lognr=message.lognr,
            total_bytes=total,
            offset=offset,
            data=data[offset : offset + frame_bytes],
            from_id=from_id,
        )
        for offset in range(0, max(total, 1), frame_bytes)
    ]
    out[0].head.CopyFrom(head_of(message))
    return out


class Relay(RelayCore):
    """A ``RelayCore`` whose writer and sender wait on each other: the stream the message
    comes on goes at the pace of the one it goes on (``room``), and the peer's stream
    waits for the next frame (``changed``)."""

    def __init__(self, lognr: int, total_bytes: int) -> None:
        super().__init__(lognr, total_bytes)
        self.changed = asyncio.Event()
        # Whether a stream is writing it now.
        self.writing = False
        self._drained = asyncio.Event()

    def add(self, frame: ring_pb2.LogFrame) -> None:
        super().add(frame)
        self.changed.set()

    async def room(self) -> None:
        """Waits while the frames not yet written fill the window and a stream is
        writing them: a relay holds a few frames, not the message. A relay no stream
        writes (the peer's stream down, or busy) does not hold its sender back."""
        while len(self.frames) >= RELAY_WINDOW_FRAMES and self.writing and not self.aborted:
            self._drained.clear()
            await self._drained.wait()

    def confirm(self) -> None:
        super().confirm()
        self.changed.set()

    def abort(self) -> None:
        super().abort()
        self.changed.set()
        self._drained.set()

    def stop_writing(self) -> None:
        """No stream writes it now: its sender is not held back."""
        self.writing = False
        self._drained.set()

    def ready(self) -> ring_pb2.LogFrame | None:
        frame = super().ready()
        if frame is not None:
            self._drained.set()
        return frame


class PeerLink:
    """The kept LogRing stream from this controller to one peer, driving its ``LinkCore``.

    ``send`` never blocks the caller (the mission program's call returns while
    the message travels). The link to the successor also has the controller's
    ``history`` (on disk), so that a successor that restarted with nothing is
    given all of it again.
    """

    def __init__(
        self,
        my_id: int,
        peer_id: int,
        address: str,
        log: BoundLogger,
        history: LogHistory | None = None,
        tls: Tls | None = None,
        frame_bytes: int = FRAME_BYTES,
        mission_id: str | None = None,
    ) -> None:
        self.my_id = my_id
        self.peer_id = peer_id
        self.address = address
        self.frame_bytes = frame_bytes
        # A peer that is a station serves many missions on its port: the stream names ours.
        self._metadata = mission_metadata(mission_id)
        self._tls = tls
        self._log = log.bind(peer=peer_id)
        self.core = LinkCore(peer_id, time.monotonic(), history)
        # Called with a handover message its receiver acknowledged (set by the node).
        self.on_handover_acked: Callable[[ring_pb2.LogMessage], None] | None = None
        # Called with the peer's id after each acknowledgement it sends.
        self.on_acked: Callable[[int], None] | None = None
        # Called when the stream comes up or goes down (the ring's route may change).
        self.on_up_down: Callable[[], None] | None = None
        # The master's word our sync frames say (``ControllerProtocol.master_word``).
        self.master_word: Callable[[], tuple[int, int]] = lambda: (0, 0)
        self.master_proof: Callable[[], ring_pb2.MasterWord | None] = lambda: None
        self._wakeup = asyncio.Event()
        self._task: asyncio.Task[None] | None = None

    @property
    def counters(self) -> PeerCounters:
        """What the link has done (the core's counters)."""
        return self.core.counters

    @property
    def stream_up(self) -> bool:
        """Whether the stream is up."""
        return self.core.up

    def start(self) -> None:
        """Starts keeping the stream."""
        if self._task is None:
            self._task = asyncio.create_task(self._run(), name=f"ring-{self.peer_id}")

    async def stop(self) -> None:
        """Stops the stream task."""
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        self.core.restarted(time.monotonic())
        self._up_down()

    def _up_down(self) -> None:
        if self.on_up_down is not None:
            self.on_up_down()

    def send(self, message: ring_pb2.LogMessage) -> None:
        """Queues ``message`` for the peer (``LinkCore.queue``); a relay of it may end."""
        self.core.queue(message, time.monotonic())
        relay = self.core.relays.get(message.lognr)
        if relay is not None:
            relay.confirm()
        self._wakeup.set()
        self.start()

    def relay(self, lognr: int, total_bytes: int) -> Relay | None:
        """Starts passing message ``lognr`` on as its frames arrive (the caller adds
        them); None if another stream's copy of it is being passed on already
        (``LinkCore.relay``)."""
        relay = Relay(lognr, total_bytes)
        if not self.core.relay(relay):
            return None
        self._wakeup.set()
        self.start()
        return relay

    def settle_handovers(self, settled: Callable[[int], bool]) -> list[ring_pb2.LogMessage]:
        """``LinkCore.settle_handovers``."""
        return self.core.settle_handovers(settled)

    @property
    def has_history(self) -> bool:
        """Whether this stream gives its receiver the history it lacks (a successor's)."""
        return self.core.history is not None

    def holds_changed(self) -> None:
        """The history grew: the successor is told what we hold (``LinkCore.sync_due``)."""
        if self.core.history is not None:
            self._wakeup.set()

    @property
    def unacked(self) -> int:
        """Messages sent and not yet acknowledged."""
        return len(self.core.unacked)

    @property
    def relaying(self) -> int:
        """The log number of the message being passed on frame by frame (0: none)."""
        written = [lognr for lognr, relay in self.core.relays.items() if relay.frames_written]
        return written[0] if written else 0

    def waiting_for_ack_s(self, now: float) -> float:
        """How long the oldest unacknowledged message has waited (0: none waits)."""
        return self.core.outbox.waiting_for_ack_s(now)

    @property
    def unacked_bytes(self) -> int:
        """The serialized size of the messages sent and not yet acknowledged."""
        return self.core.outbox.unacked_bytes

    @property
    def used(self) -> bool:
        """``LinkCore.used``."""
        return self.core.used

    async def _run(self) -> None:
        while True:
            # Said once per outage (then at debug level), unless it carries something.
            log = self._log.warning if self.core.up or self.used else self._log.debug
            try:
                await self._stream_once()
            except asyncio.CancelledError:
                raise
            except grpc.aio.AioRpcError as exc:
                log(
                    "ring stream down; reconnecting",
                    code=exc.code().name,
                    detail=exc.details(),
                    retry_in_s=self.core.backoff,
                )
            except Exception as exc:
                self._log.error("ring stream failed; reconnecting", error=repr(exc), exc_info=True)
            backoff = self.core.broken(time.monotonic())
            self._up_down()
            await asyncio.sleep(backoff)

    async def _stream_once(self) -> None:
        async with aio_channel(
            self.address, self._tls, Identity.controller(self.peer_id)
        ) as channel:
            stub = ring_pb2_grpc.ControllerRingStub(channel)
            call = stub.LogRing(wait_for_ready=True, metadata=self._metadata)
            hello = await read_message(call)
            if hello is None or not hello.hello:
                raise ConnectionError(f"peer {self.peer_id} did not greet the ring stream")
            core = self.core
            greeting = core.connected(
                hello.lognr, hello.epoch, self.master_word(), self.master_proof()
            )
            self._up_down()
            self._log.info("ring stream up", peer_lognr=hello.lognr, holds_lognr=core.synced)
            if greeting.sync is not None:
                await write_message(call, _sync_frame(greeting.sync, self.my_id))
            acks = asyncio.create_task(self._read_acks(call))
            try:
                history = core.history
                for lognr in greeting.from_history:
                    if history is not None:  # read back one message at a time
                        await self._write(call, history.get(lognr))
                while True:
                    # Cleared before looking, so a wake-up during a write is not lost.
                    self._wakeup.clear()
                    sync = core.sync_due(self.master_word(), self.master_proof())
                    if sync is not None:
                        await write_message(call, _sync_frame(sync, self.my_id))
                    pending = core.pending()
                    if not pending:
                        await _first(self._wakeup.wait(), acks, self.peer_id)
                        continue
                    for lognr in pending:
                        # The core's relays are this link's (``relay``).
                        relay = cast("Relay | None", core.relays.get(lognr))
                        if relay is not None and await self._write_relay(call, relay, acks):
                            continue
                        message = core.unacked.get(lognr)
                        if message is None:
                            continue  # acknowledged meanwhile (an earlier write of it)
                        await self._write(call, message)
            finally:
                acks.cancel()
                call.cancel()

    async def _write_relay(self, call: LogRingCall, relay: Relay, acks: asyncio.Task[None]) -> bool:
        """Writes a relayed message's frames as they come; True once all are written.

        False if it was given up: the peer is told to drop what it got, and the
        message goes whole if the protocol forwards it after all.
        """
        relay.writing = True
        try:
            return await self._write_relay_frames(call, relay, acks)
        finally:
            relay.stop_writing()
            self.counters.peak_relay_frames = max(
                self.counters.peak_relay_frames, relay.peak_buffered
            )

    async def _write_relay_frames(
        self, call: LogRingCall, relay: Relay, acks: asyncio.Task[None]
    ) -> bool:
        while True:
            relay.changed.clear()
            frame = relay.ready()
            while frame is not None:
                out = ring_pb2.LogFrame(
                    lognr=frame.lognr,
                    total_bytes=frame.total_bytes,
                    offset=frame.offset,
                    data=frame.data,
                    from_id=self.my_id,
                )
                if frame.HasField("head"):
                    out.head.CopyFrom(frame.head)
                await write_message(call, out)
                relay.wrote(frame)
                self.counters.sent_bytes += len(frame.data)
                frame = relay.ready()
            if relay.done:
                self.core.relay_written(relay)
                return True
            if relay.aborted:
                self.core.relay_given_up(relay)
                if relay.frames_written:
                    await write_message(
                        call, ring_pb2.LogFrame(lognr=relay.lognr, abort=True, from_id=self.my_id)
                    )
                return False
            await _first(relay.changed.wait(), acks, self.peer_id)

    async def _write(self, call: LogRingCall, message: ring_pb2.LogMessage) -> None:
        for frame in frames(message, self.my_id, self.frame_bytes):
            await write_message(call, frame)
            self.counters.sent_bytes += len(frame.data)
        self.core.written(message.lognr)

    async def _read_acks(self, call: LogRingCall) -> None:
        async for ack in _acks(call):
            acked = self.core.acked(ack.lognr)
            if acked.handover and acked.message and self.on_handover_acked is not None:
                self.on_handover_acked(acked.message)
            if self.on_acked is not None:
                self.on_acked(self.peer_id)


async def _first(wake: Coroutine[Any, Any, Any], acks: asyncio.Task[None], peer_id: int) -> None:
    """Waits for ``wake`` or the end of the stream's acknowledgements, which raises."""
    waiter = asyncio.create_task(wake)
    try:
        done, _ = await asyncio.wait({waiter, acks}, return_when=asyncio.FIRST_COMPLETED)
    finally:
        waiter.cancel()
    if acks in done:
        acks.result()  # raises the stream's error
        raise ConnectionError(f"peer {peer_id} closed the ring stream")


def _sync_frame(word: SyncWord, my_id: int) -> ring_pb2.LogFrame:
    """The sync frame saying ``word`` (``link_core.SyncWord``; read back by
    ``receiver_core.sync_word_of``)."""
    return ring_pb2.LogFrame(
        sync=True,
        holds_lognr=word.holds,
        holds_epoch=word.holds_epoch,
        from_id=my_id,
        master_epoch=word.master_epoch,
        master_lognr=word.master_lognr,
        holds_proof=word.holds_proof,
        holds_grant=word.holds_grant,
        master_word=word.master_proof,
    )


async def _acks(call: LogRingCall) -> AsyncIterator[ring_pb2.LogAck]:
    while True:
        ack = await read_message(call)
        if ack is None:
            return
        yield ack


class RingReceiver:
    """The receiving end of LogRing streams: each stream's frames go to a ``ReceiverCore``,
    whose actions it carries out (reassembled messages handed on, acks, relays)."""

    def __init__(
        self,
        my_id: int,
        current_lognr: Callable[[], int],
        deliver: Callable[[ring_pb2.LogMessage, int], Awaitable[None]],
        log: BoundLogger,
        max_message_bytes: int = MAX_LOG_MESSAGE_DEFAULT,
        synced: Callable[[int, SyncWord], Awaitable[None]] | None = None,
        epoch_of: Callable[[int], int] | None = None,
        relay: Callable[[ring_pb2.LogMessage, int], Relay | None] | None = None,
        arriving: Callable[[int], None] | None = None,
        held: Callable[[ring_pb2.LogMessage], bool] | None = None,
    ) -> None:
        self.my_id = my_id
        # Given a message's head: whether handling it whole would do nothing (we
        # hold it: ``ControllerProtocol.holds``), so its frames need not be kept.
        self._held = held
        # Told the log number of every frame of a message as it arrives (a message
        # on its way is not missing: ``ControllerCore.gap_due``).
        self._arriving = arriving or _told_nothing
        # Given a first frame's head and the message's size: the Relay that passes
        # its frames on as they come (cut-through), or None (store-and-forward).
        self._relay = relay
        self.max_message_bytes = max_message_bytes
        self._current_lognr = current_lognr
        # The epoch of the message with a log number we hold (the hello's, resend_after).
        self._epoch_of = epoch_of
        self._deliver = deliver
        self._synced = synced or _synced_nowhere
        self._log = log
        # Set (and replaced) by ``drop_streams``: every incoming stream ends.
        self._dropped = asyncio.Event()

    def drop_streams(self) -> None:
        """Ends every incoming stream: their senders reconnect and hear our hello again.

        After a rejoin with nothing (``ControllerNode.reset``), a predecessor
        still streaming to us would never re-send what we dropped.
        """
        dropped, self._dropped = self._dropped, asyncio.Event()
        dropped.set()

    async def serve(self, context: LogRingContext, sender: int | None = None) -> None:
        """Runs one incoming stream until the sender closes it (or ``drop_streams``).

        ``sender``: the controller the caller's certificate names (mutual TLS);
        every frame must then say it comes from that controller."""
        core = ReceiverCore(
            self.my_id, sender, self.max_message_bytes, self._relay is not None, self._held
        )
        dropped = self._dropped
        waiter = asyncio.create_task(dropped.wait())
        serving = asyncio.create_task(self._serve(context, core))
        try:
            done, _ = await asyncio.wait({waiter, serving}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            waiter.cancel()
        if serving in done:
            serving.result()
            return
        serving.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await serving
        refusal = core.dropped()
        await context.abort(refusal.code, refusal.message)

    async def _serve(self, context: LogRingContext, core: ReceiverCore) -> None:
        """Reads the stream's frames into ``core`` and carries out its actions, in order
        (``receiver_core``'s module comment)."""
        hello = core.opened(self._current_lognr(), self._epoch_of)
        await context.write(
            ring_pb2.LogAck(
                lognr=hello.lognr, hello=True, receiver_id=self.my_id, epoch=hello.epoch
            )
        )
        # The relay the core started and has not ended (its AbortRelay, SettleRelay).
        relay: Relay | None = None
        try:
            while True:
                try:
                    frame = await context.read()
                except DecodeError as exc:  # gRPC would end the stream UNKNOWN
                    actions = core.undecodable(exc)
                else:
                    if frame is grpc.aio.EOF:
                        return
                    actions = core.frame(frame)
                # StartRelay is last of its list, and its answer continues the list.
                for action in actions:
                    if isinstance(action, Arriving):
                        self._arriving(action.lognr)
                    elif isinstance(action, RelayFrame):
                        assert relay is not None
                        relay.add(action.frame)
                    elif isinstance(action, WaitForRoom):
                        assert relay is not None
                        await relay.room()
                    elif isinstance(action, Deliver):
                        await self._deliver(action.message, action.relayed_by)
                    elif isinstance(action, Ack):
                        await context.write(
                            ring_pb2.LogAck(lognr=action.lognr, receiver_id=self.my_id)
                        )
                    elif isinstance(action, StartRelay):
                        assert self._relay is not None
                        relay = self._relay(action.head, action.total_bytes)
                        actions.extend(core.relay_started(relay is not None))
                    elif isinstance(action, SettleRelay):
                        assert relay is not None
                        relay.settle()
                        relay = None
                    elif isinstance(action, AbortRelay):
                        assert relay is not None
                        relay.abort()
                        relay = None
                    elif isinstance(action, Synced):
                        await self._synced(action.sender, action.word)
                    elif isinstance(action, Refuse):
                        await context.abort(action.code, action.message)
                        return
        finally:
            if relay is not None:
                relay.abort()


def _told_nothing(lognr: int) -> None:
    """No one is told of frames arriving."""


async def _synced_nowhere(sender: int, word: SyncWord) -> None:
    """No one hears sync frames."""
