"""The node's side of a prepared handover, without processes (docs/design.md,
"Prepared handover")."""

from __future__ import annotations

from helpers.protocol import connected_session, started

from baton.config import parse_config
from baton.controller.core import PREPARE_GRACE_S, Arm, ControllerCore, Note, RingSight, Timer
from baton.controller.link_core import SyncWord
from baton.controller.node import ControllerNode
from baton.controller.protocol import State
from baton.digest import request_digest
from baton.v1 import drone_pb2, ring_pb2

POSITION = "/baton.v1.Mobility/GetPosition"


def entry(reqnr: int) -> ring_pb2.LogEntry:
    return ring_pb2.LogEntry(
        reqnr=reqnr,
        method=POSITION,
        request_digest=request_digest(POSITION, b""),
        reply=b"%d" % reqnr,
    )


async def active_master() -> ControllerNode:
    """Controller 0 of a ring of three, ACTIVE in epoch 1 (the mission's start)."""
    config = parse_config(
        {"controllers": [{"id": i, "address": f"127.0.0.1:{i + 1}"} for i in range(3)]}
    )
    node = ControllerNode(config, 0)
    session = connected_session()
    node.drone = session
    await node.on_sync(2, SyncWord(0, 0, 0, 0))  # the predecessor holds nothing: caught up
    await node.on_granted(session, drone_pb2.Connected(epoch=1))
    assert node.protocol.state is State.ACTIVE
    return node


def test_an_older_preparations_time_does_not_end_a_newer_one() -> None:
    """The drone replaced a preparation for 2 by one for 1, then by one for 2 again (a
    script's lines, each after a request). Each arms the preparation's end anew,
    replacing the older deadline (a driver's ``TimerTable`` never fires a replaced
    one): the third runs its own time, not the first one's."""
    core = ControllerCore(started(0, [0, 1, 2], 0))
    arms = []
    for target, at, timeout_s in ((2, 0.0, 0.01), (1, 1.0, 0.01), (2, 2.0, 30.0)):
        effects = core.ready(
            core.prepare(
                drone_pb2.PrepareHandover(target=target, epoch=1, timeout_s=timeout_s), now=at
            ),
            True,
            now=at,
        )
        arms += [e for e in effects if isinstance(e, Arm)]
    ends = [0.01 + PREPARE_GRACE_S, 1.01 + PREPARE_GRACE_S, 34.0]
    assert arms == [Arm(Timer.PREPARATION, end) for end in ends]
    assert core.armed == {Timer.PREPARATION: 34.0} and core.protocol.preparing_for == 2
    progress = core.progress(0)
    assert progress is not None and progress.target == 2
    over = core.timer_fired(Timer.PREPARATION, 34.0, RingSight({}, drone_connected=True))
    assert [type(e) for e in over] == [Note] and core.protocol.preparing_for is None


async def test_a_master_cut_off_from_the_drone_sends_the_target_no_copies() -> None:
    """--lose-master --prepared seed 844 (the simulation): master 0 prepared a handover
    to 2, the drone restarted and gave the role to another controller by takeover;
    0, cut off and not yet told, gave up on a call and its flush went straight to 2,
    past the taker's fence on the ring. The taker died with its log, 2 took over
    holding the give-up and built on it, while the drone had acted on that request
    for the taker's program. Copies go only while the Connect stream is up; a new
    stream's PrepareHandover catches the target up (or a refusal fences us)."""
    node = await active_master()
    await node.on_prepare(drone_pb2.PrepareHandover(target=2, epoch=1, timeout_s=10.0))
    node.drone = None  # the Connect stream broke: the session reconnects
    await node.apply(node.protocol.on_reply(entry(1)))
    assert node.peer(1).unacked == 1  # the ring has it
    assert node.peer(2).unacked == 0  # the target gets no copy
    await node.stop()
