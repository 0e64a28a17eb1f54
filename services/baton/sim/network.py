"""The simulated network: ring streams between controllers, and each controller's drone link.

Both kinds of link carry bytes with a latency, a bandwidth and some
jitter, drawn per direction from the seed (so links are slow or
asymmetric), and both break: a partition, a dropped connection, a lost
message (which resets the stream it was on, as TCP would), or an end
that died. A broken stream loses everything in flight on it.

``RingLink`` drives the shipped ``LinkCore`` (``controller/link_core.py``), as
``controller/ring.py``'s ``PeerLink`` does: what a new stream writes, what is
kept until acknowledged, when a sync frame is due and the back-off are the
core's; the link only carries frames over the virtual network. Messages are
acknowledged one by one after the receiver handled them.

``DroneLink`` is the gRPC channel between one controller and the drone
(``controller/drone_link.py``'s ``DroneSession`` uses it): calls made while
it is down wait for it (``wait_for_ready``), retried at the channel's
reconnect back-off (``rpc/channels.py``: 0.1 s doubling to 2 s); a break
fails every call in flight with UNAVAILABLE and ends the Connect stream.

Simplifications: a log message travels whole (the ``LogFrame`` slicing and
reassembly of ring.py are tested on their own); a lost message resets its
stream at once (no keep-alive delay); the receiver's hello is its
protocol's ``holds_lognr`` (as controller/service.py sends it), read when
it accepts the stream.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from baton.controller.history import LogHistory
from baton.controller.link_core import LinkCore, SyncWord
from baton.v1 import ring_pb2

if TYPE_CHECKING:
    from baton.sim.controller import SimController
    from baton.sim.world import World

DRONE = -1  # the drone's node id in partitions
# gRPC channel reconnect back-off (rpc/channels.py CHANNEL_OPTIONS).
CHANNEL_BACKOFF_MIN_S, CHANNEL_BACKOFF_MAX_S = 0.1, 2.0
# drone_link.DroneStandby's re-open back-off.
STANDBY_BACKOFF_S, STANDBY_BACKOFF_MAX_S = 0.05, 1.0


@dataclass(frozen=True)
class LinkSpec:
    """One direction of a link: latency (s), bandwidth (bit/s), jitter and reordering."""

    latency: float
    bandwidth: float
    jitter: float
    reorder: bool

    def transfer(self, size: int) -> float:
        """Seconds to put ``size`` bytes on the wire."""
        return size * 8 / self.bandwidth


class Network:
    """Link properties per direction, partitions, and the faults that act on messages."""

    def __init__(self, world: World, nodes: list[int]) -> None:
        self.world = world
        rng = world.rng
        self.specs: dict[tuple[int, int], LinkSpec] = {}
        slow_share = rng.choice((0.0, 0.0, 0.15, 0.3))
        reorder_share = rng.choice((0.0, 0.25, 0.5))
        for a in nodes:
            for b in nodes:
                if a == b:
                    continue
                drone_link = DRONE in (a, b)
                latency = rng.uniform(0.001, 0.02) if drone_link else rng.uniform(0.001, 0.03)
                bandwidth = rng.choice((5e6, 25e6, 100e6))
                if rng.random() < slow_share:  # a slow direction: the other may be fast
                    latency *= rng.uniform(5, 40)
                    bandwidth /= rng.uniform(5, 50)
                self.specs[a, b] = LinkSpec(
                    latency, bandwidth, rng.uniform(0.0, 0.5), rng.random() < reorder_share
                )
        self.cuts: dict[frozenset[int], int] = {}
        # Message faults, on while the fault window lasts (World.faulty).
        self.p_loss = rng.choice((0.0, 0.002, 0.01, 0.03))
        self.p_dup = rng.choice((0.0, 0.01, 0.05))

    def reachable(self, a: int, b: int) -> bool:
        """Whether no partition separates ``a`` and ``b``."""
        return not self.cuts.get(frozenset((a, b)))

    def cut(self, a: int, b: int, break_links: bool = True) -> None:
        """Partitions ``a`` from ``b`` (counted: overlapping partitions heal one by one);
        the links between them break, unless ``break_links`` is False (none is open yet)."""
        key = frozenset((a, b))
        self.cuts[key] = self.cuts.get(key, 0) + 1
        world = self.world
        if not break_links:
            return
        for x, y in ((a, b), (b, a)):
            if x == DRONE:
                world.controller(y).drone_link.break_("partition")
            elif y != DRONE:
                link = world.controller(x).links.get(y)
                if link is not None:
                    link.break_("partition")

    def heal(self, a: int, b: int) -> None:
        """Ends one partition between ``a`` and ``b``; the links reconnect on their own."""
        key = frozenset((a, b))
        self.cuts[key] -= 1
        if not self.cuts[key]:
            del self.cuts[key]

    def delay(self, a: int, b: int, size: int = 0) -> float:
        """Latency with jitter plus transfer time from ``a`` to ``b``."""
        spec = self.specs[a, b]
        return spec.latency * (1 + spec.jitter * self.world.rng.random()) + spec.transfer(size)

    def lose(self, link: RingLink) -> bool:
        """Whether this message is lost (and its stream reset)."""
        return self.world.faulty and self.p_loss > 0 and self.world.rng.random() < self.p_loss

    def duplicate(self) -> bool:
        """Whether this message is delivered twice."""
        return self.world.faulty and self.p_dup > 0 and self.world.rng.random() < self.p_dup


class RingLink:
    """The kept LogRing stream from one controller to one peer, driving its ``LinkCore``
    (as ring.py's ``PeerLink`` does) over the virtual network.

    Owned by one controller incarnation: a killed controller's links die
    with it, unacknowledged messages included.
    """

    def __init__(
        self, world: World, owner: SimController, dest: int, history: LogHistory | None
    ) -> None:
        self.world = world
        self.owner = owner
        self.dest = dest
        self.core = LinkCore(dest, world.loop.now, history)
        self.generation = 0
        self._peer: SimController | None = None
        self._started = False
        self._tx_free = 0.0
        self._fifo = 0.0
        self.peak_unacked = 0
        self.stopped = False  # PeerLink.stop: no more attempts
        self._try = 0  # the connection attempt under way; a restart supersedes it
        owner.ring_changed()

    @property
    def up(self) -> bool:
        """Whether the stream is up."""
        return self.core.up

    @property
    def history(self) -> LogHistory | None:
        """The history this stream gives (a successor's), or None."""
        return self.core.history

    @property
    def unacked(self) -> dict[int, ring_pb2.LogMessage]:
        """The messages sent and not yet acknowledged, by log number."""
        return self.core.unacked

    def start(self) -> None:
        """Starts keeping the stream (PeerLink.start)."""
        if not self._started:
            self._started = True
            self._attempt()

    def send(self, message: ring_pb2.LogMessage) -> None:
        """PeerLink.send (``LinkCore.queue``); written at once if the stream is up."""
        self.core.queue(message, self.world.loop.now)
        self.peak_unacked = max(self.peak_unacked, len(self.unacked))
        self._write_pending()
        self.start()

    def break_(self, why: str) -> None:
        """The stream broke: everything in flight is lost; reconnect after the back-off."""
        if not self.up:
            return  # a connection attempt in progress sees it for itself
        self.generation = self.world.next_id()
        self.world.trace(f"ring {self.owner.id}->{self.dest} down ({why})")
        self.owner.ring_changed()
        self._retry()

    def stop(self) -> None:
        """PeerLink.stop: the stream ends, no more attempts, unacknowledged messages dropped."""
        self.stopped = True
        self._try += 1
        if self.up:
            self.core.restarted(self.world.loop.now)
            self.generation = self.world.next_id()

    def restart(self) -> None:
        """PeerLink.stop and start (node.py ``_routed``): a new stream, whose hello and
        history re-send use the history given (``RingLinks.rerouted``). A stream not up
        yet reads the history when it comes up."""
        if self.up:
            self.core.restarted(self.world.loop.now)
            self.generation = self.world.next_id()
            self._try += 1
            self._attempt(self._try)

    # -- connecting ---------------------------------------------------------------

    def _retry(self) -> None:
        wait = self.core.broken(self.world.loop.now)
        self.world.loop.after(wait, self._attempt, self._try)

    def _usable_peer(self) -> SimController | None:
        world, me = self.world, self.owner
        peer = world.controller(self.dest)
        if me.alive and peer.alive and world.net.reachable(me.id, self.dest):
            return peer
        return None

    def _attempt(self, attempt: int | None = None) -> None:
        if not self.owner.alive or self.stopped:
            return
        if attempt is not None and attempt != self._try:
            return  # superseded by a restart
        peer = self._usable_peer()
        if peer is None:
            self._retry()
            return
        delay = self.world.net.delay(self.owner.id, self.dest)
        self.world.loop.after(delay, self._accepted, peer, self._try)

    def _accepted(self, peer: SimController, attempt: int) -> None:
        """At the receiver (RingReceiver.serve): the hello says the log number it holds."""
        if not self.owner.alive or attempt != self._try:
            return
        if self._usable_peer() is not peer:
            self._retry()
            return
        hello = peer.protocol.holds_lognr  # controller/service.py's current_lognr
        epoch = peer.protocol.epoch_of(hello) if hello else 0  # and epoch_of
        self.world.loop.after(
            self.world.net.delay(self.dest, self.owner.id),
            self._greeted,
            peer,
            hello,
            attempt,
            epoch,
        )

    def _greeted(self, peer: SimController, hello: int, attempt: int, epoch: int = 0) -> None:
        """PeerLink._stream_once after the hello: the core's greeting, then the kept ones."""
        if not self.owner.alive or attempt != self._try:
            return
        if self._usable_peer() is not peer:
            self._retry()
            return
        self._peer = peer
        self.generation = self.world.next_id()
        self._tx_free = self._fifo = self.world.loop.now
        p = self.owner.protocol
        greeting = self.core.connected(hello, epoch, p.master_word, p.master_proof)
        self.world.trace(
            f"ring {self.owner.id}->{self.dest} up (hello {hello}, holds {self.core.synced})"
        )
        self.world.check_start()
        if greeting.sync is not None:
            self._deliver_later(0, self._sync_frame, greeting.sync)
        history = self.history
        for lognr in greeting.from_history:
            if history is not None and self.up:
                self._write(history.get(lognr))
        self._write_pending()
        self.owner.ring_changed()  # back to a natural successor that is up again

    def holds_changed(self) -> None:
        """PeerLink.holds_changed: a sync frame when the core says one is due."""
        if not self.owner.alive:
            return
        sync = self.core.sync_due(self.owner.protocol.master_word, self.owner.protocol.master_proof)
        if sync is not None:
            self._deliver_later(0, self._sync_frame, sync)

    # -- frames -------------------------------------------------------------------

    def _write_pending(self) -> None:
        for lognr in self.core.pending():
            if not self.up:
                return  # a lost message broke the stream
            self._write(self.unacked[lognr])

    def _write(self, message: ring_pb2.LogMessage) -> None:
        self.core.written(message.lognr)
        if self.world.net.lose(self):
            self.world.trace(f"ring {self.owner.id}->{self.dest} lost message {message.lognr}")
            self.break_("message lost")
            return
        data = message.SerializeToString()
        self._deliver_later(len(data), self._message_frame, data)
        if self.world.net.duplicate():
            self._deliver_later(len(data), self._message_frame, data)

    def _deliver_later(self, size: int, handler: Callable[..., None], arg: Any) -> None:
        net = self.world.net
        spec = net.specs[self.owner.id, self.dest]
        now = self.world.loop.now
        self._tx_free = max(self._tx_free, now) + spec.transfer(size)
        if spec.reorder:
            arrival = self._tx_free + spec.latency * self.world.rng.uniform(0.2, 3.0)
        else:
            arrival = max(self._tx_free + net.delay(self.owner.id, self.dest), self._fifo)
            self._fifo = arrival
        self.world.loop.at(arrival, self._arrive, self.generation, handler, arg)

    def _arrive(self, generation: int, handler: Callable[..., None], arg: Any) -> None:
        if generation != self.generation or not self.up or not self.owner.alive:
            return
        peer = self._peer
        if peer is None or not peer.alive:
            return
        handler(peer, arg)

    def _sync_frame(self, peer: SimController, sync: SyncWord) -> None:
        peer.on_sync(self.owner.id, sync)

    def _message_frame(self, peer: SimController, data: bytes) -> None:
        message = ring_pb2.LogMessage.FromString(data)
        peer.on_log(message)
        self.world.loop.after(
            self.world.net.delay(self.dest, self.owner.id),
            self._ack,
            self.generation,
            message.lognr,
        )

    def _ack(self, generation: int, lognr: int) -> None:
        if generation == self.generation and self.up and self.owner.alive:
            acked = self.core.acked(lognr)
            if acked.handover and acked.message is not None:  # PeerLink.on_handover_acked
                self.owner.handover_acked(acked.message)
            self.owner.target_acked(self.dest)  # PeerLink.on_acked


class DroneLink:
    """One controller incarnation's gRPC channel to the drone."""

    def __init__(self, world: World, owner: SimController) -> None:
        self.world = world
        self.owner = owner
        self.generation = self.world.next_id()
        self._waiters: list[tuple[Callable[..., None], tuple[Any, ...]]] = []
        self._polling = False
        self._backoff = CHANNEL_BACKOFF_MIN_S
        self._stream_fifo = 0.0

    def usable(self) -> bool:
        """The drone is up, this controller alive, and no partition between them."""
        world = self.world
        return world.drone.up and self.owner.alive and world.net.reachable(self.owner.id, DRONE)

    def when_usable(self, callback: Callable[..., None], *args: Any) -> None:
        """Runs ``callback`` once the channel is ready (a call with ``wait_for_ready``)."""
        self._waiters.append((callback, args))
        if not self._polling:
            self._polling = True
            self.world.loop.after(self._backoff, self._poll)

    def _poll(self) -> None:
        if not self.owner.alive:
            return
        if not self.usable():
            self._backoff = min(self._backoff * 2, CHANNEL_BACKOFF_MAX_S)
            self.world.loop.after(self._backoff, self._poll)
            return
        self._polling = False
        self._backoff = CHANNEL_BACKOFF_MIN_S
        waiters, self._waiters = self._waiters, []
        for callback, args in waiters:
            callback(*args)

    def to_drone(self, size: int, handler: Callable[..., None], *args: Any) -> None:
        """Sends to the drone on the current connection (the caller checked ``usable``)."""
        delay = self.world.net.delay(self.owner.id, DRONE, size)
        self.world.loop.after(delay, self._at_drone, self.generation, handler, args)

    def _at_drone(self, generation: int, handler: Callable[..., None], args: tuple[Any]) -> None:
        if generation == self.generation and self.world.drone.up:
            handler(*args)

    def to_controller(
        self, generation: int, size: int, handler: Callable[..., None], *args: Any, stream: bool
    ) -> None:
        """Sends to the controller over connection ``generation``; lost if it has broken.

        Events of one Connect stream stay in order; Invoke replies race them
        (footnote 2: the reply and the handover notice may arrive either way).
        """
        if generation != self.generation:
            return
        arrival = self.world.loop.now + self.world.net.delay(DRONE, self.owner.id, size)
        if stream:
            arrival = self._stream_fifo = max(arrival, self._stream_fifo)
        self.world.loop.at(arrival, self._at_controller, generation, handler, args)

    def stream_to_controller(
        self, generation: int, parts: list[tuple[int, Callable[..., None], tuple[Any, ...]]]
    ) -> None:
        """Sends ``parts`` (size, handler, args) in order on the Connect stream, back to
        back: one latency for them all (one jitter draw, like one message), each part
        arriving once the bytes before it and its own crossed."""
        if generation != self.generation:
            return
        latency = self.world.net.delay(DRONE, self.owner.id, 0)
        spec = self.world.net.specs[DRONE, self.owner.id]
        sent = 0
        for size, handler, args in parts:
            sent += size
            arrival = self.world.loop.now + latency + spec.transfer(sent)
            arrival = self._stream_fifo = max(arrival, self._stream_fifo)
            self.world.loop.at(arrival, self._at_controller, generation, handler, args)

    def _at_controller(
        self, generation: int, handler: Callable[..., None], args: tuple[Any]
    ) -> None:
        if generation == self.generation and self.owner.alive:
            handler(*args)

    def _standby_again(self, generation: int, backoff: float) -> None:
        """DroneStandby's re-open loop: once the drone is reachable, the stream is up."""
        if generation != self.generation or not self.owner.alive:
            return  # broken again (that break re-opens it), or the controller is gone
        if not self.usable():
            backoff = min(backoff * 2, STANDBY_BACKOFF_MAX_S)
            self.world.loop.after(backoff, self._standby_again, generation, backoff)
            return
        self.world.drone.standby_opened(self.owner.id)

    def break_(self, why: str) -> None:
        """The connection broke: calls in flight fail, the Connect stream ends, at both ends."""
        old, self.generation = self.generation, self.world.next_id()
        world = self.world
        world.trace(f"drone link of {self.owner.id} down ({why})")
        world.drone.link_broke(self.owner.id, old)
        if self.owner.alive:
            world.loop.after(world.rng.uniform(0.005, 0.3), self.owner.on_drone_link_broken, old)
            if world.drone.core.takeover_owed(self.owner.id) is not None:
                # drone_link.DroneStandby opens its stream again (back-off from
                # STANDBY_BACKOFF_S); the drone tells a TakeOver still owed on it.
                world.loop.after(
                    STANDBY_BACKOFF_S, self._standby_again, self.generation, STANDBY_BACKOFF_S
                )
