"""A drone session's events handed to its controller node, each as a task of its own
on the node's event loop, with the session they came on (a session closed meanwhile
is ignored by the node)."""

from __future__ import annotations

from collections.abc import Coroutine, Sequence
from typing import TYPE_CHECKING, Any

from baton.controller.core import DroneRefusal
from baton.tasks import TaskSet
from baton.v1 import drone_pb2

if TYPE_CHECKING:
    from baton.controller.drone_link import DroneSession
    from baton.controller.node import ControllerNode


class SessionEvents:
    """A drone session's events, handed to the node on its event loop with the session."""

    def __init__(self, node: ControllerNode, tasks: TaskSet) -> None:
        self._node = node
        self._tasks = tasks  # the node's: each event runs as a task of its own
        self.session: DroneSession | None = None

    def _run(self, event: Coroutine[Any, Any, None]) -> None:
        self._tasks.spawn(event, name="drone-event")

    def granted(self, connected: drone_pb2.Connected) -> None:
        assert self.session is not None
        self._run(self._node.on_granted(self.session, connected))

    def retained(self, replies: Sequence[drone_pb2.RetainedReply]) -> None:
        assert self.session is not None
        # A task like granted's: tasks start in the order they are made, so the
        # batch is taken after the Connected event's on_granted began (and reset).
        self._run(self._node.on_retained(self.session, replies))

    def notice(self, notice: drone_pb2.HandoverNotice) -> None:
        assert self.session is not None
        self._run(self._node.on_stream_notice(self.session, notice))

    def prepare(self, prepare: drone_pb2.PrepareHandover) -> None:
        self._run(self._node.on_prepare(prepare))

    def refused(self, refusal: DroneRefusal) -> None:
        assert self.session is not None
        self._run(self._node.on_connect_refused(self.session, refusal))

    def down(self) -> None:
        self._node.drone_streams_changed()
