"""What a controller node waits for, judged every half second (stalls.py), for GetStatus
and the log: the conditions are ``status.holding``'s, pure, given what the node sees."""

from __future__ import annotations

import asyncio
import time
from typing import TYPE_CHECKING

from baton.controller.status import Sight, holding
from baton.stalls import StallWatch, Wait, controller_judge, one_line

if TYPE_CHECKING:
    from baton.controller.node import ControllerNode


class StallWatcher:
    """What one ``ControllerNode`` waits for, kept for GetStatus."""

    def __init__(self, node: ControllerNode) -> None:
        self.node = node
        self._stalls = StallWatch()
        self.stalled: list[Wait] = []  # a missing log message, a ring stream down, ...

    def conditions(self) -> dict[str, str]:
        """What holds now that would be a stall if it lasted (stalls.py)."""
        node = self.node
        drone, link = node.drone, node.ring.get(node.protocol.successor)
        sight = Sight(
            drone=None if drone is None else (drone.address, drone.connected.is_set()),
            standby_address=node.standby.address,
            standby_up=node.standby.up,
            in_flight=node.program.in_flight,
            operator_pause=drone.operator_pause if drone is not None else "",
            successor_link=None if link is None else (link.stream_up, link.unacked),
        )
        return holding(node.protocol, node.routed_around, sight)

    async def run(self) -> None:
        """Every half second: stalls into the status, and into the log when they begin."""
        node = self.node
        while True:
            node.history.poll()  # a failed checkpoint is said within this period
            now = time.monotonic()
            judge = controller_judge(
                node.config.handover_policy.name != "none",
                node.protocol.master,
                node.config.prepare_timeout,
            )
            self.stalled = self._stalls.update(now, self.conditions(), judge)
            if self._stalls.due_for_log(now, self.stalled):
                node.log.warning("stalled", waiting=one_line(self.stalled))
            await asyncio.sleep(0.5)
