"""A program call's flow (call_flow.CallFlow), driven by hand: the turns both drivers run."""

from __future__ import annotations

import grpc
import pytest
from helpers.protocol import started

from baton.controller.call_flow import (
    Apply,
    CallFlow,
    Invoke,
    Invoked,
    LookAtSession,
    Pause,
    ReadClock,
    RetriesEnded,
    SessionSeen,
    WaitConnected,
)
from baton.controller.core import CLOCK_NOW, ControllerCore
from baton.controller.protocol import State

POSITION = "/baton.v1.Mobility/GetPosition"


def master() -> ControllerCore:
    """Controller 0 of ring 0 -> 1 -> 2, ACTIVE master in epoch 1."""
    core = ControllerCore(started(0, [0, 1, 2], 0), True)
    assert core.protocol.state is State.ACTIVE
    return core


def up(now: float) -> SessionSeen:
    return SessionSeen(present=True, connected=True, epoch=1, now=now)


def test_a_drone_call_is_sent_in_the_sessions_epoch_and_its_reply_logged() -> None:
    core = master()
    flow = CallFlow(core, POSITION, b"", retry_limit_s=300.0)
    steps = flow.run()
    assert isinstance(next(steps), LookAtSession)
    invoke = steps.send(up(0.0))
    assert isinstance(invoke, Invoke)
    assert (invoke.sent.reqnr, invoke.sent.epoch, flow.reqnr) == (1, 1, 1)
    applied = steps.send(Invoked(0.1, (b"here", 1, b"")))
    assert isinstance(applied, Apply)  # logged: seen, and flushed (limit 0)
    try:
        steps.send(None)
    except StopIteration as stop:
        assert stop.value.reqnr == 1 and stop.value.reply == b"here"
    else:
        raise AssertionError("the flow did not end with the logged entry")


def test_an_unavailable_drone_is_sent_the_same_request_after_growing_pauses_then_fails() -> None:
    core = master()
    steps = CallFlow(core, POSITION, b"", retry_limit_s=1.0).run()
    next(steps)
    sent = steps.send(up(0.0))
    assert isinstance(sent, Invoke)
    pauses = []
    io = steps.send(Invoked(0.0, None, grpc.StatusCode.UNAVAILABLE, "no vehicle"))
    while isinstance(io, Pause):
        pauses.append(io.seconds)
        assert isinstance(steps.send(None), LookAtSession)
        again = steps.send(up(sum(pauses)))
        assert isinstance(again, Invoke) and again.sent == sent.sent  # the same request
        io = steps.send(Invoked(sum(pauses), None, grpc.StatusCode.UNAVAILABLE, "no vehicle"))
    assert pauses == pytest.approx([0.2, 0.4, 0.4])  # doubling, cut to what the limit leaves
    assert isinstance(io, RetriesEnded) and io.reqnr == 1
    logged = steps.send(None)
    assert isinstance(logged, Apply)
    seen = [e for e in logged.effects if hasattr(e, "entry")]
    assert seen and seen[0].entry.status_code == grpc.StatusCode.UNAVAILABLE.value[0]


def test_without_a_session_the_core_is_asked_again_and_a_stream_down_is_waited_for() -> None:
    core = master()
    flow = CallFlow(core, POSITION, b"", retry_limit_s=300.0)
    steps = flow.run()
    next(steps)
    assert isinstance(steps.send(SessionSeen(False, False, 0, 0.0)), LookAtSession)
    assert isinstance(steps.send(SessionSeen(True, False, 0, 0.0)), WaitConnected)
    assert isinstance(steps.send(None), LookAtSession)
    assert isinstance(steps.send(up(0.0)), Invoke)
    assert flow.reqnr == 1  # one request number throughout


def test_a_clock_call_is_answered_here_and_a_give_up_is_logged_for_its_request() -> None:
    core = master()
    flow = CallFlow(core, CLOCK_NOW, b"", retry_limit_s=300.0)
    steps = flow.run()
    assert isinstance(next(steps), ReadClock)
    given_up = flow.gave_up(grpc.StatusCode.DEADLINE_EXCEEDED)
    entries = [e.entry for e in given_up if hasattr(e, "entry")]
    assert entries and entries[0].reqnr == 1 and entries[0].given_up
