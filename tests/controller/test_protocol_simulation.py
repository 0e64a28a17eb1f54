"""Whole rings of ControllerProtocol under random message orders.

A small discrete simulation: N controllers, each with the same deterministic
mission program, a drone with duplicate detection and scripted handovers,
FIFO links between controllers, and a scheduler that picks at random which
pending event happens next (a ring message, a drone reply, a handover notice,
a program step). Whatever the order, every replica must see the same replies
and the drone must execute every request exactly once.
"""

from __future__ import annotations

import random
from collections import deque
from dataclasses import dataclass, field
from typing import Any, cast

import pytest
from helpers.protocol import started

from baton.controller.protocol import (
    ConnectDrone,
    DisconnectDrone,
    SendLog,
    State,
    TookOver,
    request_digest,
)
from baton.v1 import ring_pb2


def program(calls: int) -> list[tuple[str, bytes]]:
    methods = ["/baton.v1.Mobility/GetPosition", "/baton.v1.Camera/TakePicture"]
    return [(methods[i % 7 == 0], i.to_bytes(4, "big")) for i in range(calls)]


@dataclass
class Drone:
    master: int
    handovers: dict[int, int]  # after reqnr -> new master
    executed: list[int] = field(default_factory=list)
    cache: dict[int, bytes] = field(default_factory=dict)

    def invoke(self, cid: int, reqnr: int, method: str) -> tuple[str, object]:
        if cid != self.master:
            return "rejected", self.master
        if reqnr in self.cache:
            return "reply", self.cache[reqnr]
        assert reqnr == (self.executed[-1] + 1 if self.executed else 1), "request skipped"
        self.executed.append(reqnr)
        self.cache[reqnr] = f"{method}#{reqnr}".encode()
        return "reply", self.cache[reqnr]


class Ring:
    def __init__(self, n: int, flush: int, handovers: dict[int, int], calls: int, seed: int):
        self.rng = random.Random(seed)
        self.ids = list(range(n))
        self.p = {i: started(i, self.ids, flush) for i in self.ids}
        self.links: dict[tuple[int, int], deque[ring_pb2.LogMessage]] = {}
        self.drone = Drone(0, handovers)
        self.program = program(calls)
        self.seen: dict[int, list[bytes]] = {i: [] for i in self.ids}
        self.in_flight: dict[int, tuple[int, deque[tuple[str, object]]]] = {}
        self.notices: dict[int, deque[int]] = {i: deque() for i in self.ids}
        self.done: set[int] = set()

    def apply(self, cid: int, effects: list) -> None:
        for e in effects:
            if isinstance(e, SendLog):
                self.links.setdefault((cid, e.dest), deque()).append(e.message)
            else:
                assert isinstance(e, ConnectDrone | DisconnectDrone | TookOver)

    def step(self) -> bool:
        choices: list[tuple[str, Any]] = []
        choices += [("link", key) for key, q in self.links.items() if q]
        choices += [("reply", cid) for cid, (_, q) in self.in_flight.items() if q]
        choices += [("notice", cid) for cid, q in self.notices.items() if q]
        choices += [("program", cid) for cid in self.ids if self.can_step(cid)]
        if not choices:
            return False
        kind, key = self.rng.choice(choices)
        getattr(self, f"do_{kind}")(key)
        return True

    def can_step(self, cid: int) -> bool:
        p = self.p[cid]
        if cid in self.done or cid in self.in_flight:
            return False
        return p.state is State.REPLAY or (p.state is State.ACTIVE)

    def do_link(self, key: tuple[int, int]) -> None:
        _, dst = key
        self.apply(dst, self.p[dst].on_log(self.links[key].popleft()))

    def do_notice(self, cid: int) -> None:
        self.apply(cid, self.p[cid].on_handover_notice(self.notices[cid].popleft()))

    def do_program(self, cid: int) -> None:
        p = self.p[cid]
        index = len(self.seen[cid])
        method, request = self.program[index]
        if p.state is State.REPLAY:
            got, effects = p.replay(method, request)
            self.answer(cid, got.reply)
            self.apply(cid, effects)
            return
        reqnr = p.reqnr + 1
        outcome = self.drone.invoke(cid, reqnr, method)
        self.in_flight[cid] = (reqnr, deque([outcome]))
        if outcome[0] == "reply" and reqnr in self.drone.handovers and self.drone.master == cid:
            # Scripted: hand over right after serving reqnr; the notice races the reply.
            new = self.drone.handovers.pop(reqnr)
            self.drone.master = new
            self.notices[cid].append(new)

    def do_reply(self, cid: int) -> None:
        reqnr, outcomes = self.in_flight.pop(cid)
        kind, value = outcomes.popleft()
        p = self.p[cid]
        if kind == "rejected":
            self.apply(cid, p.on_handover_notice(cast(int, value)))
            return
        if p.state is not State.ACTIVE or p.reqnr + 1 != reqnr:
            return  # the notice overtook the reply: discarded, the new master re-sends
        method, request = self.program[reqnr - 1]
        e = ring_pb2.LogEntry(
            reqnr=reqnr,
            method=method,
            reply=value,  # type: ignore[arg-type]
            request=request,
            request_digest=request_digest(method, request),
        )
        self.apply(cid, p.on_reply(e))
        self.answer(cid, e.reply)

    def answer(self, cid: int, reply: bytes) -> None:
        self.seen[cid].append(reply)
        if len(self.seen[cid]) == len(self.program):
            self.done.add(cid)
            self.apply(cid, self.p[cid].on_mission_done())

    def run(self) -> None:
        for _ in range(200_000):
            if not self.step():
                return
        raise AssertionError("simulation did not settle")


def expected_replies(calls: int) -> list[bytes]:
    return [f"{m}#{i + 1}".encode() for i, (m, _) in enumerate(program(calls))]


@pytest.mark.parametrize("seed", range(40))
@pytest.mark.parametrize(
    ("n", "flush", "handovers"),
    [
        (2, 0, {5: 1, 11: 0, 17: 1}),
        (2, 400, {5: 1, 11: 0, 17: 1}),
        (6, 0, {4: 1, 9: 4, 15: 3, 22: 2}),  # 1, 3, 5 and 5 hops
        (6, 250, {4: 1, 9: 4, 15: 3, 22: 2}),
        (3, 10**6, {3: 2, 6: 1, 7: 0, 8: 2}),  # nothing flushed between handovers
    ],
)
def test_every_replica_sees_the_same_replies_and_the_drone_executes_each_once(
    seed: int, n: int, flush: int, handovers: dict[int, int]
) -> None:
    calls = 30
    ring = Ring(n, flush, dict(handovers), calls, seed)
    ring.run()
    assert ring.drone.executed == list(range(1, calls + 1))
    assert ring.drone.handovers == {}, "every scripted handover happened"
    for cid in ring.ids:
        assert ring.seen[cid] == expected_replies(calls), f"controller {cid} diverged"
    masters = [cid for cid, p in ring.p.items() if p.master]
    assert masters == [ring.drone.master]
