"""A controller's masterships as one value, and the combinations the protocol never makes."""

from __future__ import annotations

import dataclasses

import pytest
from helpers.protocol import started

from baton.controller.core import ControllerCore
from baton.controller.mastership import Mastership, State
from baton.drone.invariants import InvariantBroken
from baton.v1 import ring_pb2

REPLICA = Mastership(
    state=State.PASSIVE,
    master=False,
    epoch=0,
    granted=0,
    took_over_in=0,
    owed=0,
    over=0,
    flushed_in=0,
    fenced=False,
    fenced_in=0,
    before_handover=0,
)
MASTER = dataclasses.replace(REPLICA, state=State.ACTIVE, master=True, epoch=3, granted=3)


def test_a_replica_and_an_active_master_are_legal() -> None:
    assert REPLICA.problems() == [] and MASTER.problems() == []
    taker = dataclasses.replace(MASTER, took_over_in=3)
    assert taker.taker and taker.problems() == []
    assert not dataclasses.replace(taker, master=False, state=State.PASSIVE).taker


@pytest.mark.parametrize(
    ("change", "said"),
    [
        ({"master": False}, "ACTIVE without the role"),
        ({"fenced": True, "fenced_in": 4}, "ACTIVE though fenced"),
        ({"state": State.PASSIVE, "epoch": 0, "granted": 0}, "master in no epoch"),
        ({"over": 3}, "a mastership of ours that is over"),
        ({"granted": 4}, "granted epoch 4, newer than our epoch 3"),
        ({"took_over_in": 5}, "took over in epoch 5"),
        ({"flushed_in": 4}, "flushed in epoch 4"),
        ({"before_handover": 4}, "epoch before the handover 4 past 3"),
        ({"owed": 2}, "owed the handover message of epoch 2, ours is 3"),
        (
            {"state": State.PASSIVE, "master": False, "fenced": True, "fenced_in": 3},
            "fenced by epoch 3, not newer than ours 3",
        ),
    ],
)
def test_each_combination_the_protocol_never_makes_is_named(change: dict, said: str) -> None:
    problems = dataclasses.replace(MASTER, **change).problems()
    assert any(said in problem for problem in problems), problems


def test_a_cooperative_grant_whose_handover_message_never_came_is_a_mastership_over() -> None:
    """Granted epoch 3 cooperatively, we wait for its handover message; the ring's log
    goes on in epoch 4 without it: that role went on without us. Our epoch stays the
    drone's grant, over (we never acted in it: our Connect names none), and nothing is
    owed. (It went back to epoch 0 before, older than the drone's grant.)"""
    p = started(1, [0, 1, 2], 2**20)
    p.on_granted(3)
    assert p.master and p.state is State.PASSIVE and p.mastership.owed == 3
    message = ring_pb2.LogMessage(lognr=1, origin=2, epoch=4)
    p.on_log(message)
    m = p.mastership
    assert (m.master, m.epoch, m.granted, m.over, m.owed) == (False, 3, 3, 3, 0)
    assert m.problems() == [] and p.log_mastership_epoch == 0


def test_the_core_stops_on_an_illegal_mastership_when_checking() -> None:
    p = started(0, [0, 1, 2], 2**20)
    core = ControllerCore(p)
    core.checking = True
    assert core.ready([], drone_connected=True, now=0.0)  # legal: the mastership is kept
    p.fenced, p._fenced_in = True, 2  # ACTIVE though fenced: never made by the protocol
    with pytest.raises(InvariantBroken, match="ACTIVE though fenced"):
        core.ready([], drone_connected=True, now=0.0)
