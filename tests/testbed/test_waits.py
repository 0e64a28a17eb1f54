"""The progress line warns about what needs a person, and only that: a station out of
radio range by design is shown as expected; a real stall is still a warning."""

from __future__ import annotations

import io
from pathlib import Path

from baton.config import load_config
from baton.testbed.local import Snapshot
from baton.testbed.run import Progress
from baton.testbed.waits import out_of_range, sort_waits, waits_line
from baton.v1 import drone_pb2, ring_pb2

CORRIDOR = load_config(Path(__file__).resolve().parents[2] / "examples" / "corridor.yaml")
# Over station 1's antenna: out of station 3's range (1,000 m east).
OVER_STATION_1 = (47.3981912, 8.5522295)
NO_STANDBY = (
    "no standby stream to the drone at 127.0.0.1:33673: the drone cannot make this "
    "controller master if the master is lost for 26 s"
)
RING_DOWN = "ring stream to controller 2 down (3 messages not acknowledged) for 5 s"


def corridor_line(waiting: dict[int, str]) -> str:
    """The progress line the corridor shows with the vehicle over station 1."""
    out = io.StringIO()
    progress = Progress(16, 0, stream=out)
    progress.config = CORRIDOR
    drone = drone_pb2.DroneStatus(master=1)
    drone.position.latitude_deg, drone.position.longitude_deg = OVER_STATION_1
    snapshot = Snapshot(drone, vehicle_effects=None, camera_effects=None)
    for cid in range(4):
        snapshot.controllers[cid] = ring_pb2.ControllerStatus(
            id=cid, master=cid == 1, waiting=waiting.get(cid, "")
        )
    progress(snapshot)
    return out.getvalue()


def test_the_corridor_shows_no_warning_for_stations_out_of_range() -> None:
    assert out_of_range(CORRIDOR, 3, OVER_STATION_1)
    line = corridor_line({3: NO_STANDBY})
    assert "waiting" not in line, line
    assert "out of range, as planned: c3" in line


def test_a_real_stall_is_still_warned() -> None:
    # A ring stream down is never explained by range.
    line = corridor_line({3: f"{NO_STANDBY}; {RING_DOWN}"})
    assert f"c3 waiting: {RING_DOWN}" in line
    assert "out of range, as planned: c3" in line
    # A station in range without its standby stream is a link that should be up.
    assert not out_of_range(CORRIDOR, 1, OVER_STATION_1)
    line = corridor_line({1: NO_STANDBY})
    assert f"c1 waiting: {NO_STANDBY}" in line
    assert "as planned" not in line


def test_without_radio_range_every_wait_is_a_warning() -> None:
    grid = CORRIDOR.model_copy(update={"radio_range": False})
    assert not out_of_range(grid, 3, OVER_STATION_1)
    assert waits_line(grid, {3: NO_STANDBY}, OVER_STATION_1) == f" | c3 waiting: {NO_STANDBY}"


def test_an_unknown_position_explains_nothing() -> None:
    assert not out_of_range(CORRIDOR, 3, None)
    assert sort_waits(NO_STANDBY, beyond_range=False).warnings == [NO_STANDBY]
