"""The node's side of a prepared handover, without processes (docs/design.md,
"Prepared handover")."""

from __future__ import annotations

from typing import Any

from baton.config import parse_config
from baton.controller.node import ControllerNode
from baton.controller.protocol import State
from baton.v1 import drone_pb2


async def test_the_progress_word_counts_the_acks_of_a_stream_opened_since_it_began() -> None:
    """--lose-master --prepared seed 816 (the simulation): the master's stream to the
    target was dropped (the ring routed back past it, ``_route``) and opened again, and
    its acknowledgements counted from 0: the word's ``acked`` was the new stream's count
    less the old one's, negative, and building the Invoke raised ValueError. A stream
    opened since the preparation began counts all its acknowledgements."""
    config = parse_config(
        {"controllers": [{"id": i, "address": f"127.0.0.1:{i + 1}"} for i in range(3)]}
    )
    node = ControllerNode(config, 0)
    session: Any = object()
    node._drone = session
    await node.on_sync(2, 0)  # the predecessor holds nothing: caught up
    await node.on_granted(session, 1, 0)
    assert node.protocol.state is State.ACTIVE
    old = node.peer(2)
    old.counters.acked = 5  # acknowledgements of messages sent before
    await node.on_prepare(drone_pb2.PrepareHandover(target=2, epoch=1, timeout_s=10.0))
    assert node.protocol.preparing_for == 2
    progress = node._preparation_progress()
    assert progress is not None and progress.acked == 0  # none since it began
    await old.stop()
    del node._peers[2]  # as _route drops a stream that holds nothing unacknowledged
    new = node.peer(2)
    new.counters.acked = 2
    progress = node._preparation_progress()
    assert progress is not None and progress.target == 2 and progress.acked == 2
    node._drone = None
    await node.stop()
