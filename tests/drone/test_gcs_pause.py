"""A ground station's override pauses the mission (issue 32, item 5): DroneCore's decision,
fed requests at chosen times (no sockets)."""

from __future__ import annotations

import grpc
import pytest

from baton.digest import request_digest
from baton.drone.core import DroneCore
from baton.drone.sequencer import Sequencer
from baton.rpc.errors import StatusError
from baton.v1 import drone_pb2

GET = "/baton.v1.Mobility/GetPosition"
DIGEST = request_digest(GET, b"")


def request(reqnr: int, cid: int = 0) -> drone_pb2.InvokeRequest:
    return drone_pb2.InvokeRequest(controller_id=cid, epoch=1, reqnr=reqnr, method=GET)


def test_paused_by_a_ground_station_the_masters_next_request_is_refused_until_resumed() -> None:
    drone = DroneCore(Sequencer([0, 1], initial_master=0), 1.0)
    drone.pause_by_ground_station("paused by ground station 255 (MAV_CMD_NAV_LAND)")
    with pytest.raises(StatusError) as refused:
        drone.admit(request(1), DIGEST, 1.0)
    assert refused.value.code is grpc.StatusCode.FAILED_PRECONDITION
    assert "paused by ground station 255 (MAV_CMD_NAV_LAND)" in refused.value.message
    assert drone.seq.last_reqnr == 0  # nothing admitted: the number stays unused
    drone.resume_from_ground_station()
    admitted = drone.admit(request(1), DIGEST, 2.0)
    assert admitted.cached is None
