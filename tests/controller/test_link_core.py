"""One ring link's send side, fed events at chosen times (``controller/link_core.py``),
and a controller's set of links (``controller/links.py``): the pure pieces both the
runtime's ``PeerLink`` and the simulation's ``RingLink`` drive."""

from __future__ import annotations

from helpers.protocol import started

from baton.controller.core import ControllerCore, RouteTo
from baton.controller.history import LogHistory
from baton.controller.link_core import BACKOFF_INITIAL_S, BACKOFF_MAX_S, LinkCore, RelayCore
from baton.controller.links import RingLinks
from baton.v1 import drone_pb2, ring_pb2


def message(lognr: int, epoch: int = 1, handover: bool = False) -> ring_pb2.LogMessage:
    return ring_pb2.LogMessage(lognr=lognr, origin=0, epoch=epoch, handover=handover)


def history_of(*lognrs: int, epoch: int = 1) -> LogHistory:
    history = LogHistory()
    for lognr in lognrs:
        history.add(message(lognr, epoch))
    return history


def test_a_successors_new_stream_syncs_then_gives_what_it_lacks_then_what_is_unacked() -> None:
    history = history_of(1, 2, 3, 4)
    core = LinkCore(1, now=0.0, history=history)
    core.queue(message(4), now=0.0)  # kept unacknowledged: goes with the unacked ones
    core.queue(message(5), now=0.0)
    greeting = core.connected(hello_lognr=2, hello_epoch=1, word=(1, 3))
    assert greeting.sync is not None
    assert (greeting.sync.holds, greeting.sync.holds_epoch) == (4, 1)
    assert (greeting.sync.master_epoch, greeting.sync.master_lognr) == (1, 3)
    assert greeting.from_history == [3]
    assert core.pending() == [4, 5]
    core.written(4)
    core.written(5)
    assert core.pending() == []


def test_a_hello_of_an_older_framing_gets_its_own_number_again() -> None:
    """The peer handled message 2 of epoch 1; ours is of epoch 2 (a takeover framed it
    again): it is given from 2 on (``resend_after``)."""
    core = LinkCore(1, now=0.0, history=history_of(1, 2, 3, epoch=2))
    assert core.connected(hello_lognr=2, hello_epoch=1, word=(2, 0)).from_history == [2, 3]


def test_a_stream_to_a_handover_target_carries_only_what_was_sent_on_it() -> None:
    core = LinkCore(2, now=0.0)
    core.queue(message(7, handover=True), now=0.0)
    greeting = core.connected(hello_lognr=0, hello_epoch=0, word=(1, 0))
    assert greeting.sync is None and greeting.from_history == []
    assert core.pending() == [7]
    assert core.sync_due((2, 5)) is None  # no history: it never says what it holds


def test_a_break_forgets_what_was_written_and_the_backoff_doubles_until_up() -> None:
    core = LinkCore(1, now=0.0)
    core.queue(message(1), now=0.0)
    core.connected(0, 0, (0, 0))
    core.written(1)
    assert core.down_since is None  # up
    waits = [core.broken(now=10.0) for _ in range(8)]
    assert waits[:3] == [BACKOFF_INITIAL_S, 2 * BACKOFF_INITIAL_S, 4 * BACKOFF_INITIAL_S]
    assert waits[-1] == BACKOFF_MAX_S
    assert core.down_since == 10.0  # down since the first break, not the last
    assert core.pending() == [1]  # written again on the next stream
    core.connected(0, 0, (0, 0))
    assert core.broken(now=20.0) == BACKOFF_INITIAL_S  # a stream that came up starts over


def test_a_number_queued_again_is_written_again_and_its_ack_releases_it_once() -> None:
    core = LinkCore(1, now=0.0)
    core.connected(0, 0, (0, 0))
    core.queue(message(3, handover=True), now=1.0)
    core.written(3)
    core.queue(message(3, handover=True), now=2.0)  # a former master sends it on again
    assert core.pending() == [3]
    acked = core.acked(3)
    assert acked.handover and acked.message is not None and acked.message.lognr == 3
    again = core.acked(3)
    assert again.message is None and not again.handover
    assert core.counters.acked == 2 and core.unacked == {}


def test_a_sync_is_due_when_the_history_grew_or_the_masters_word_changed() -> None:
    history = history_of(1)
    core = LinkCore(1, now=0.0, history=history)
    assert core.sync_due((1, 0)) is None  # not up
    core.connected(0, 0, (1, 0))
    assert core.sync_due((1, 0)) is None
    history.add(message(2))
    sync = core.sync_due((1, 0))
    assert sync is not None and sync.holds == 2
    assert core.sync_due((1, 0)) is None
    word = core.sync_due((2, 2))
    assert word is not None and (word.holds, word.master_epoch, word.master_lognr) == (2, 2, 2)


def test_a_link_is_used_once_it_carries_something() -> None:
    core = LinkCore(2, now=0.0)
    assert not core.used  # kept open for a handover to come
    core.queue(message(1), now=0.0)
    assert core.used
    assert LinkCore(1, now=0.0, history=LogHistory()).used


def test_a_relays_last_frame_waits_for_the_protocols_forward() -> None:
    relay = RelayCore(4, total_bytes=6)
    for offset in (0, 3):
        relay.add(ring_pb2.LogFrame(lognr=4, total_bytes=6, offset=offset, data=b"abc"))
    first = relay.ready()
    assert first is not None and first.offset == 0
    relay.wrote(first)
    assert relay.ready() is None and not relay.done  # the last one: not forwarded yet
    relay.confirm()
    last = relay.ready()
    assert last is not None
    relay.wrote(last)
    assert relay.done


def test_a_relay_not_forwarded_is_aborted_when_settled() -> None:
    relay = RelayCore(4, total_bytes=3)
    relay.add(ring_pb2.LogFrame(lognr=4, total_bytes=3, offset=0, data=b"abc"))
    relay.settle()
    assert relay.aborted and relay.ready() is None


def frame_of(lognr: int, offset: int = 0, total: int = 3) -> ring_pb2.LogFrame:
    return ring_pb2.LogFrame(lognr=lognr, total_bytes=total, offset=offset, data=b"abc")


def forwarded(core: LinkCore, relay: RelayCore) -> None:
    """The protocol forwarded the relayed message whole (``PeerLink.send``)."""
    core.queue(message(relay.lognr), now=0.0)
    relay.confirm()


def test_a_relay_a_stream_took_a_frame_of_ends_with_it_and_its_message_goes_whole() -> None:
    """The stream ends between taking the relayed message's frame and writing it (grpc
    refuses a write on a call that finished): the frame is gone with it, so the relay
    is given up, and the next stream writes the message whole, kept unacknowledged."""
    core = LinkCore(1, now=0.0, history=history_of(1, 2))
    core.connected(hello_lognr=1, hello_epoch=1, word=(1, 0))
    relay = RelayCore(2, total_bytes=3)
    assert core.relay(relay)
    relay.add(frame_of(2))
    forwarded(core, relay)
    assert core.pending() == [2]
    assert relay.ready() is not None  # taken; its write fails
    core.broken(now=1.0)
    assert relay.aborted and core.relays == {}
    assert core.counters.relays_aborted == 1
    greeting = core.connected(hello_lognr=1, hello_epoch=1, word=(1, 0))
    assert greeting.from_history == [] and core.pending() == [2]


def test_a_relay_a_stream_ended_mid_way_of_is_given_up_and_its_message_goes_whole() -> None:
    """A relay part-written on a stream that broke (or was restarted) cannot go on
    from where it was on the next: the receiver dropped its part with the stream."""
    for end in ("broken", "restarted"):
        core = LinkCore(1, now=0.0, history=history_of(1))
        core.connected(hello_lognr=1, hello_epoch=1, word=(1, 0))
        relay = RelayCore(2, total_bytes=6)
        core.relay(relay)
        relay.add(frame_of(2))
        first = relay.ready()
        assert first is not None
        relay.wrote(first)
        getattr(core, end)(1.0)
        assert relay.aborted and core.relays == {}, end
        relay.add(frame_of(2, offset=3))  # the rest arrives, and is forwarded whole
        core.queue(message(2), now=1.0)
        core.connected(hello_lognr=1, hello_epoch=1, word=(1, 0))
        assert core.pending() == [2], end


def test_a_relay_no_stream_took_a_frame_of_is_written_on_the_next_stream() -> None:
    core = LinkCore(1, now=0.0, history=history_of(1))
    core.connected(hello_lognr=1, hello_epoch=1, word=(1, 0))
    relay = RelayCore(2, total_bytes=3)
    core.relay(relay)
    relay.add(frame_of(2))  # its last frame: waits for the forward, so nothing is taken
    assert relay.ready() is None
    core.broken(now=1.0)
    assert not relay.aborted and core.relays == {2: relay}
    core.connected(hello_lognr=1, hello_epoch=1, word=(1, 0))
    forwarded(core, relay)
    assert core.pending() == [2]
    last = relay.ready()
    assert last is not None and last.offset == 0
    relay.wrote(last)
    assert relay.done
    core.relay_written(relay)
    assert core.pending() == [] and core.relays == {}
    assert (core.counters.relayed_messages, core.counters.relays_aborted) == (1, 0)


def test_a_message_is_relayed_by_one_stream_at_a_time() -> None:
    """A second copy of a message being relayed is not relayed; once that relay is
    given up, a new copy takes its place, and the old one's end leaves it there."""
    core = LinkCore(1, now=0.0)
    old, new = RelayCore(2, total_bytes=3), RelayCore(2, total_bytes=3)
    assert core.relay(old)
    assert not core.relay(new)
    old.abort()
    assert core.relay(new)
    core.relay_given_up(old)
    assert core.relays == {2: new} and core.pending() == [2]


class FakeLink:
    """A link as ``RingLinks`` sees one: its core, what was sent, how often it synced."""

    def __init__(self, pid: int, history: LogHistory | None) -> None:
        self.core = LinkCore(pid, 0.0, history)
        self.syncs = 0

    def send(self, message: ring_pb2.LogMessage) -> None:
        self.core.queue(message, 0.0)

    def holds_changed(self) -> None:
        self.syncs += 1


def links_of(cid: int = 0, ring: tuple[int, ...] = (0, 1, 2)) -> RingLinks[FakeLink]:
    core = ControllerCore(started(cid, list(ring), 0))
    return RingLinks(LogHistory(), lambda: core.protocol.successor, FakeLink)


def test_only_the_successors_link_carries_the_history() -> None:
    links = links_of()
    assert links.peer(1).core.history is links.history
    assert links.peer(2).core.history is None


def test_a_handover_message_enters_the_history_when_acknowledged_or_settled() -> None:
    links = links_of()
    target = links.peer(2)
    target.send(message(3, handover=True))
    links.settle_handovers(lambda lognr: False)
    assert 3 not in links.history
    links.settle_handovers(lambda lognr: True)
    assert 3 in links.history and not target.core.unacked[3].handover
    assert links.peer(1).syncs == 1
    links.handover_acked(message(3, handover=True))  # held already: nothing again
    assert links.peer(1).syncs == 1


def test_a_reroute_gives_the_history_and_retires_a_link_that_owes_nothing() -> None:
    links = links_of()
    links.peer(1)
    plan = links.rerouted(RouteTo(successor=2, skipped=[1], previous=1, natural=1))
    assert plan.needs_history and plan.link.core.history is links.history
    # Back to the natural successor 1 from 2, routed to before.
    back = RouteTo(successor=1, skipped=[], previous=2, natural=1)
    owing = links.peer(2)
    owing.send(message(1))
    assert links.rerouted(back).retired is None  # it owes one
    # It carries what it owes, not the history: only the successor's link gives that.
    assert owing.core.history is None and links.peer(1).core.history is links.history
    owing.core.acked(1)
    plan = links.rerouted(back)
    assert plan.retired is owing and not plan.needs_history and 2 not in links.links


def test_the_progress_word_counts_the_acks_of_a_stream_opened_since_it_began() -> None:
    """The master's stream to a preparation's target was dropped (the ring routed back
    past it) and a new one made: its acknowledgements count from 0, never less the old
    stream's count (a negative ``acked`` made building the Invoke raise)."""
    core = ControllerCore(started(0, [0, 1, 2], 0))
    links = RingLinks(LogHistory(), lambda: core.protocol.successor, FakeLink)
    old = links.peer(2)
    old.core.counters.acked = 5  # acknowledgements of messages sent before
    core.prepare(drone_pb2.PrepareHandover(target=2, epoch=1, timeout_s=10.0), now=0.0)
    links.preparing(2)
    progress = links.progress(core, now=0.0)
    assert progress is not None and progress.acked == 0  # none since it began
    del links.links[2]  # as a reroute retires a link that owes nothing
    links.peer(2).core.counters.acked = 2
    progress = links.progress(core, now=0.0)
    assert progress is not None and progress.target == 2 and progress.acked == 2


def test_a_link_routed_back_to_while_up_is_given_what_the_history_gained_meanwhile() -> None:
    """Controller 0 of ring 0 -> 1 -> 2 -> 3 routes around 1 to 2, then around 1 and 2
    to 3 (2 skipped), then back to 2. 2's stream, up all along, kept the history: no
    greeting gives it what the history gained while the route was elsewhere, so the
    reroute does (a taker behind it waited for it for ever). It is not started again: a
    stream slower to come up than the detection time would be routed around again,
    and back, for ever. A skipped link still counts for the route while down."""
    links = links_of(ring=(0, 1, 2, 3))
    natural = links.peer(1)
    plan = links.rerouted(RouteTo(successor=2, skipped=[1], previous=1, natural=1))
    assert plan.needs_history and natural.core.history is links.history
    assert 1 in links.down_since()
    to_2 = plan.link
    to_2.core.connected(0, 0, (0, 0))
    links.keep(message(1))
    to_2.send(message(1))  # sent to 2, the successor, as ever
    plan = links.rerouted(RouteTo(successor=3, skipped=[1, 2], previous=2, natural=1))
    assert to_2.core.history is links.history  # skipped: kept for when the route is back
    links.keep(message(2))
    links.keep(message(3))  # kept while 3 is the successor: 2 never saw them
    plan = links.rerouted(RouteTo(successor=2, skipped=[1], previous=3, natural=1))
    assert plan.link is to_2 and not plan.needs_history and plan.retired is not None
    assert to_2.core.pending() == [1, 2, 3]  # what it had not acknowledged, and the gain
    assert to_2.core.left_at is None and 3 not in links.links
