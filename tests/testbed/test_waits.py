"""The progress line and the report show expected waits quietly and stalls loudly, as
each part judged them: a station out of radio range by design is "out of range, as
planned"; a real stall is a "NEEDS A PERSON"."""

from __future__ import annotations

import io

from baton.testbed.local import Snapshot
from baton.testbed.run import Progress
from baton.testbed.waits import LOUD, WaitLog, part_waits, report_lines, waits_line
from baton.v1 import drone_pb2, ring_pb2, waits_pb2

NO_STANDBY = waits_pb2.Wait(
    key="standby",
    text="no standby stream to the drone at 127.0.0.1:33673: the drone cannot make this "
    "controller master if the master is lost",
    age_s=26.0,
    needs_person=False,
)
RING_DOWN = waits_pb2.Wait(
    key="ring",
    text="ring stream to controller 2 down (3 messages not acknowledged)",
    age_s=5.0,
    needs_person=True,
)
LINK_1 = waits_pb2.Wait(
    key="link 1",
    text="controller 1 holds no standby stream though the vehicle is in its range",
    age_s=6.0,
    needs_person=True,
)


def snapshot(drone: list[waits_pb2.Wait], controllers: dict[int, list[waits_pb2.Wait]]) -> Snapshot:
    """Four controllers, 1 master, with these waits."""
    taken = Snapshot(drone_pb2.DroneStatus(master=1, waits=drone))
    for cid in range(4):
        taken.controllers[cid] = ring_pb2.ControllerStatus(
            id=cid, master=cid == 1, waits=controllers.get(cid, [])
        )
    return taken


def progress_line(taken: Snapshot) -> str:
    out = io.StringIO()
    Progress(16, 0, stream=out)(taken)
    return out.getvalue()


def test_stations_out_of_range_are_named_once_as_planned_and_warn_nothing() -> None:
    line = progress_line(snapshot([], {0: [NO_STANDBY], 3: [NO_STANDBY]}))
    assert line.rstrip().endswith("| out of range, as planned: c0, c3"), line
    assert LOUD not in line and "waiting" not in line


def test_a_real_stall_is_still_warned_beside_the_expected() -> None:
    line = progress_line(snapshot([], {3: [NO_STANDBY, RING_DOWN]}))
    assert "| out of range, as planned: c3" in line
    assert line.rstrip().endswith(
        f"| {LOUD}: c3: ring stream to controller 2 down (3 messages not acknowledged) for 5 s"
    ), line


def test_a_station_the_drone_finds_in_range_is_not_shown_out_of_range() -> None:
    # Station 1 says its missing stream may be range; the drone, which sees the
    # vehicle in its range, says the link should be up.
    taken = snapshot([LINK_1], {1: [NO_STANDBY], 3: [NO_STANDBY]})
    line = waits_line(part_waits(taken.drone, taken.controllers))
    assert line == (
        " | out of range, as planned: c3"
        f" | {LOUD}: drone: controller 1 holds no standby stream though the vehicle is in "
        "its range for 6 s"
    )


def test_the_report_keeps_each_wait_once_with_its_longest_age() -> None:
    log = WaitLog()
    early = snapshot([], {3: [NO_STANDBY]})
    log.add(part_waits(early.drone, early.controllers), 4.0)
    # The same station's Connect and standby streams: one "out of range" in the report.
    drone_link = waits_pb2.Wait(key="drone", age_s=35.0)
    later = snapshot([], {3: [waits_pb2.Wait(key="standby", age_s=40.0), drone_link, RING_DOWN]})
    log.add(part_waits(later.drone, later.controllers), 30.0)
    waits = log.to_json()
    assert waits == {
        "needs_person": [
            {"part": "c3", "key": "ring", "first_s": 30.0, "longest_s": 5.0, "text": RING_DOWN.text}
        ],
        "expected": [
            {
                "part": "c3",
                "key": "standby",
                "first_s": 4.0,
                "longest_s": 40.0,
                "text": "out of range",
            }
        ],
    }
    assert report_lines(waits) == [
        "expected waits: c3 out of range (up to 40 s)",
        f"{LOUD}: c3: {RING_DOWN.text} (up to 5 s, first seen 30 s into the run)",
    ]
    assert report_lines({"needs_person": [], "expected": []}) == []
