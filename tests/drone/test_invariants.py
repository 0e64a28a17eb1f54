"""The drone's own invariants (baton.drone.invariants): the checks a running drone makes
at every request it admits when BATON_CHECK_INVARIANTS=1, and the simulation after every
event."""

from __future__ import annotations

import pytest

from baton.drone.core import DroneCore
from baton.drone.invariants import DroneWatch, InvariantBroken
from baton.drone.sequencer import Sequencer
from baton.v1 import drone_pb2


def test_two_controllers_in_one_epoch_break_it() -> None:
    watch = DroneWatch()
    assert watch.accepted(1, 0, 1) is None
    assert watch.accepted(1, 0, 2) is None
    assert watch.accepted(2, 1, 3) is None
    problem = watch.accepted(2, 0, 4)
    assert problem == "epoch 2: requests of controller 1 and of controller 0 (reqnr 4) accepted"


@pytest.mark.parametrize(
    ("now", "broken"),
    [
        ((2, 10, 5), None),
        ((1, 10, 5), "the drone's epoch went back from 2 to 1"),
        ((2, 9, 5), "the drone's last reqnr went back from 10 to 9"),
        ((2, 10, 4), "the drone's watermark went back from 5 to 4"),
        ((2, 10, 11), "the drone's watermark 11 is past its last reqnr 10"),
    ],
)
def test_the_epoch_the_last_reqnr_and_the_watermark_never_move_back(
    now: tuple[int, int, int], broken: str | None
) -> None:
    watch = DroneWatch()
    assert watch.moved(2, 10, 5) is None
    assert watch.moved(*now) == broken


def test_a_checking_core_stops_at_the_admission_that_breaks_one() -> None:
    core = DroneCore(Sequencer([0, 1], 0), watch=DroneWatch())
    first = drone_pb2.InvokeRequest(controller_id=0, epoch=1, reqnr=1, method="/baton.v1.Clock/Now")
    core.admit(first, b"d", 0.0)
    core.seq.served(0, 1, first.method, b"d", b"", 0.0, 0.0)
    assert core.watch is not None
    core.watch.last_reqnr = 5  # as if the drone had served up to 5 before
    second = drone_pb2.InvokeRequest(
        controller_id=0, epoch=1, reqnr=2, method="/baton.v1.Clock/Now"
    )
    with pytest.raises(InvariantBroken, match="last reqnr went back from 5 to 1"):
        core.admit(second, b"e", 0.1)
