"""A testbed's snapshot: the drone is read after the controllers (no processes)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from baton.testbed.local import LocalTestbed
from baton.v1 import drone_pb2, ring_pb2


class _World:
    """A mission of two drone calls that goes on by one call at each status read, as a
    mission does while a loaded machine answers the reads one by one."""

    def __init__(self) -> None:
        self.executed = 1  # the first call done, the second under way

    def step(self) -> None:
        self.executed = min(self.executed + 1, 2)


class _Drone:
    def __init__(self, world: _World) -> None:
        self.world = world

    async def GetStatus(self, request: Any, **_: Any) -> drone_pb2.DroneStatus:
        audit = [drone_pb2.AuditEntry(reqnr=n) for n in range(1, self.world.executed + 1)]
        self.world.step()
        return drone_pb2.DroneStatus(
            last_reqnr=len(audit),
            audit=audit,
            preparing_for=-1,  # no preparation
        )


class _Controller:
    def __init__(self, world: _World) -> None:
        self.world = world

    async def GetStatus(self, request: Any, **_: Any) -> ring_pb2.ControllerStatus:
        self.world.step()
        done = self.world.executed == 2
        mission = ring_pb2.MISSION_STATE_DONE if done else ring_pb2.MISSION_STATE_RUNNING
        return ring_pb2.ControllerStatus(mission=mission, reqnr=self.world.executed)


async def test_a_snapshot_that_says_the_missions_ended_holds_every_drone_call() -> None:
    """test_a_diverging_mission_is_stopped_with_both_requests_shown failed on a loaded
    machine with an empty drone audit though the master's mission was done: the
    snapshot read the drone's status first and the controllers' after, while the
    mission's three calls went on. Read after the controllers, the drone holds at least
    what they say they did."""
    world = _World()
    testbed: Any = object.__new__(LocalTestbed)
    testbed.drone_stub = _Drone(world)
    testbed.controller_stubs = {0: _Controller(world), 1: _Controller(world)}
    testbed.supervisor = SimpleNamespace(parts={})
    testbed.held_down = set()
    testbed.dead = set()
    testbed.counted_effects = lambda: (None, None)
    snapshot = await LocalTestbed.snapshot(testbed)
    assert snapshot.missions_ended
    assert [a.reqnr for a in snapshot.drone.audit] == [1, 2]
