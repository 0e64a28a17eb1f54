"""The node's reading of the drone's Connected event, without processes (issue 10)."""

from __future__ import annotations

import asyncio
from typing import Any

import grpc
from helpers.protocol import connected_session

from baton.config import parse_config
from baton.controller.link_core import SyncWord
from baton.controller.node import ControllerNode
from baton.controller.protocol import State
from baton.digest import request_digest
from baton.rpc.errors import StatusError
from baton.v1 import drone_pb2, ring_pb2

POSITION = "/baton.v1.Mobility/GetPosition"
DIGEST = request_digest(POSITION, b"")


def entry(reqnr: int) -> ring_pb2.LogEntry:
    return ring_pb2.LogEntry(
        reqnr=reqnr, method=POSITION, request_digest=DIGEST, reply=b"%d" % reqnr
    )


async def test_a_taker_with_nothing_is_granted_by_the_connected_event_alone() -> None:
    """--lose-master seed 1092: taker 2 sent a request, then its log diverged from the
    ring's and it rejoined with nothing. No TakeOver is told again after a request, so
    its fresh self knew only the Connected event: it took the grant for a cooperative
    one and waited for ever for a handover message of epoch 6. The Connected says
    takeover, and the drone's watermark now (2: the retained replies start at 3): the
    taker goes ACTIVE once the ring gave it every request up to 2, not before (it would
    frame the retained replies after a gap) and not never."""
    config = parse_config(
        {"controllers": [{"id": i, "address": f"127.0.0.1:{i + 1}"} for i in range(3)]}
    )
    node = ControllerNode(config, 2)
    session = connected_session()
    node.drone = session  # the session the Connected came on
    retained = [
        drone_pb2.RetainedReply(reqnr=3, method=POSITION, request_digest=DIGEST, reply=b"3")
    ]
    await node.on_granted(
        session, drone_pb2.Connected(epoch=6, retained_through=3, takeover=True, watermark_reqnr=2)
    )
    await node.on_retained(session, retained)
    p = node.protocol
    assert p.master and p.state is State.PASSIVE and not p.caught_up
    # Holding nothing, it holds the log number it must (0): only the watermark holds it.
    assert p.catch_up_to == 0 and p.must_hold_reqnr == 2 and p.state is State.PASSIVE
    await node.on_sync(1, SyncWord(1, 0, 0, 0))
    message = ring_pb2.LogMessage(lognr=1, origin=0, epoch=1, entries=[entry(1), entry(2)])
    await node.on_log(message)
    assert p.held_reqnr == 2 and p.caught_up  # no handover message owed
    assert p.state is State.REPLAY  # the program replays 1 and 2, then goes ACTIVE
    assert list(node.core.retained) == [3]
    node.drone = None
    await node.stop()


def kept(reqnr: int) -> drone_pb2.RetainedReply:
    return drone_pb2.RetainedReply(
        reqnr=reqnr, method=POSITION, request_digest=DIGEST, reply=b"%d" % reqnr
    )


async def settle() -> None:
    """Lets every task that can run do so (nothing here waits on time or sockets)."""
    for _ in range(20):
        await asyncio.sleep(0)


class NoDrone:
    """A session the node must not send to: every reply it needs is retained."""

    connected = asyncio.Event()

    async def invoke(self, *args: object, **kwargs: object) -> None:
        raise AssertionError(f"sent to the drone: {args}")

    async def close(self) -> None:
        pass


async def taker_of_three() -> tuple[ControllerNode, Any, list[int]]:
    """Controller 1 of three, in sync with its predecessor and holding a drone session
    that answers nothing; the list is the request number at each rejoin."""
    config = parse_config(
        {"controllers": [{"id": i, "address": f"127.0.0.1:{i + 1}"} for i in range(3)]}
    )
    node = ControllerNode(config, 1)
    rejoins: list[int] = []

    async def on_rejoin() -> None:
        rejoins.append(node.protocol.reqnr)

    node.on_rejoin = on_rejoin
    session: Any = NoDrone()
    node.drone = session
    await node.on_sync(0, SyncWord(0, 0, 0, 0))
    return node, session, rejoins


async def test_a_taker_answers_its_program_from_each_retained_batch_as_it_comes() -> None:
    """The retained tail follows the Connected event in batches: a call whose reply is
    still crossing waits for its batch (it is not sent to the drone, nor answered by the
    controller's clock); a Connected again (the stream broke mid-way) says what is still
    to come, and the rest arrives on the new stream."""
    config = parse_config(
        {"controllers": [{"id": i, "address": f"127.0.0.1:{i + 1}"} for i in range(3)]}
    )
    node = ControllerNode(config, 1)
    session: Any = NoDrone()
    node.drone = session
    await node.on_sync(0, SyncWord(0, 0, 0, 0))
    await node.on_granted(
        session, drone_pb2.Connected(epoch=2, retained_through=3, takeover=True, watermark_reqnr=0)
    )
    p = node.protocol
    assert p.state is State.ACTIVE and node.core.retained_through == 3

    first = asyncio.create_task(node.program.call(POSITION, b""))
    await settle()
    assert not first.done()  # its batch has not come
    await node.on_retained(session, [kept(1)])
    assert (await asyncio.wait_for(first, 5)).reply == b"1"

    second = asyncio.create_task(node.program.call(POSITION, b""))
    await settle()
    assert not second.done()
    # The stream broke before the next batch: the Connect again says 2 and 3 are to come.
    await node.on_granted(
        session, drone_pb2.Connected(epoch=2, retained_through=3, takeover=True, watermark_reqnr=0)
    )
    await node.on_retained(session, [kept(2), kept(3)])
    assert (await asyncio.wait_for(second, 5)).reply == b"2"
    assert (await node.program.call(POSITION, b"")).reply == b"3"
    assert node.answered_from_retained == 3 and p.reqnr == 3
    node.drone = None
    await node.stop()


async def test_a_taker_holding_a_replaced_framing_rejoins_before_it_sends_a_request() -> None:
    """--policy nearest seed 132: the taker holds request 2 as a cut-off master framed it
    in epoch 1 (its Clock reading), and a takeover in epoch 3 brought another to the
    drone. Its Connected (epoch 7) is followed by the replies it holds too: the program's
    next call waits for them, and the taker rejoins with nothing on request 2 instead
    of building on a reading no other controller has."""
    node, session, rejoins = await taker_of_three()
    await node.on_log(ring_pb2.LogMessage(lognr=1, origin=0, epoch=1, entries=[entry(1)]))
    await node.on_log(ring_pb2.LogMessage(lognr=2, origin=0, epoch=1, entries=[entry(2)]))
    await node.on_granted(
        session, drone_pb2.Connected(epoch=7, retained_through=2, takeover=True, watermark_reqnr=0)
    )
    p = node.protocol
    assert (await node.program.call(POSITION, b"")).reply == b"1"  # replayed from the log
    assert (await node.program.call(POSITION, b"")).reply == b"2"
    assert p.state is State.ACTIVE and p.held_reqnr == 2
    third = asyncio.create_task(node.program.call(POSITION, b""))
    await settle()
    assert not third.done()  # the batches of the replies we hold have not come
    await node.on_retained(session, [kept(1)])
    await settle()
    assert not third.done() and not rejoins  # the same outcome: the ring's
    replaced = kept(2)
    replaced.reply, replaced.epoch = b"another reading", 3
    await node.on_retained(session, [replaced])
    await settle()
    assert rejoins == [2]
    third.cancel()
    node.drone = None
    await node.stop()


async def test_a_give_up_of_a_retained_reply_a_lost_master_acted_on_is_not_logged() -> None:
    """--lose-master seeds 2456 and 2707: the new master's program gave up on request 1
    while its retained reply was crossing, and the master logged the give-up; but the
    drone had served the lost master requests 2 and 3 after its program had that reply.
    The entry is the retained reply (what the mission had), and the program, which saw
    a give-up, starts again (it has acted on nothing: every call so far was retained).
    The master's log is flushed first and kept for its fresh self (``restart_program``):
    it may be the only copy left (--lose-master seeds 10688, 11795)."""
    node, session, rejoins = await taker_of_three()
    await node.on_granted(
        session, drone_pb2.Connected(epoch=2, retained_through=3, takeover=True, watermark_reqnr=0)
    )
    p = node.protocol
    assert p.state is State.ACTIVE and node.core.retained_through == 3

    first = asyncio.create_task(node.program.call(POSITION, b""))
    await settle()
    first.cancel()  # the program gives up while the batch crosses
    await settle()
    assert p.reqnr == 0  # not logged as given up
    await node.on_retained(session, [kept(1), kept(2), kept(3)])
    second = asyncio.create_task(node.program.call(POSITION, b""))
    try:
        await asyncio.wait_for(second, 5)
        raise AssertionError("the program went on past a give-up the log contradicts")
    except StatusError as err:
        assert err.code is grpc.StatusCode.ABORTED
    await settle()
    assert p.reqnr == 1 and node.program.restarts == 1 and rejoins == [1]
    assert not p.log and p.lognr == 1 and p.kept_history() == 1
    flushed = node.history.get(1).entries
    assert not flushed[-1].given_up and flushed[-1].reply == b"1"
    node.drone = None
    await node.stop()


async def test_a_give_up_of_the_last_retained_reply_is_logged() -> None:
    """No program acted on the last retained reply (the drone served nothing after it):
    the new master's give-up of it is the call's outcome, as a master's give-up of its
    last request is (and goes to the drone with the next request)."""
    config = parse_config(
        {"controllers": [{"id": i, "address": f"127.0.0.1:{i + 1}"} for i in range(3)]}
    )
    node = ControllerNode(config, 1)
    session: Any = NoDrone()
    node.drone = session
    await node.on_sync(0, SyncWord(0, 0, 0, 0))
    await node.on_granted(
        session, drone_pb2.Connected(epoch=2, retained_through=1, takeover=True, watermark_reqnr=0)
    )
    p = node.protocol
    first = asyncio.create_task(node.program.call(POSITION, b""))
    await settle()
    first.cancel()
    await settle()
    assert p.reqnr == 1 and p.log.entries[-1].given_up
    assert node.program.restarts == 0 and 1 not in node.core.retained
    node.drone = None
    await node.stop()


async def test_a_give_up_before_the_connected_event_waits_for_what_the_drone_retains() -> None:
    """--lose-master seed 2456: master 0, ACTIVE by a handover message (epoch 3) from a
    taker that handed over at once, gave up on request 1 before the drone's Connected
    came, and logged the give-up; the Connected then said the drone retains the lost
    master's replies 1 to 3. Until the Connected of the mastership, a give-up is held
    like one given up while waiting, and settled from what the drone retains."""
    node, session, rejoins = await taker_of_three()
    handover = ring_pb2.LogMessage(lognr=1, origin=1, handover=True, sender=0, epoch=3)
    await node.on_log(handover)
    p = node.protocol
    assert p.state is State.ACTIVE and p.granted_epoch != p.epoch

    first = asyncio.create_task(node.program.call(POSITION, b""))
    await settle()
    first.cancel()
    await settle()
    assert p.reqnr == 0  # not logged: the drone may retain an answer
    await node.on_granted(
        session, drone_pb2.Connected(epoch=3, retained_through=3, takeover=False, watermark_reqnr=0)
    )
    await node.on_retained(session, [kept(1), kept(2), kept(3)])
    second = asyncio.create_task(node.program.call(POSITION, b""))
    try:
        await asyncio.wait_for(second, 5)
        raise AssertionError("the program went on past a give-up the log contradicts")
    except StatusError as err:
        assert err.code is grpc.StatusCode.ABORTED
    await settle()
    assert p.reqnr == 1 and rejoins == [1] and p.kept_history() == p.lognr == 2
    assert not node.history.get(2).entries[-1].given_up  # flushed for the fresh self
    node.drone = None
    await node.stop()
