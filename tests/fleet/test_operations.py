"""The operator's questions to stations: a silent station is said within the deadline,
and a mission's overview reads the master, state and progress from its sessions."""

from __future__ import annotations

import socket
import time

import pytest

from baton.config import BatonConfig
from baton.fleet import operations
from baton.fleet.operations import ask_stations, overview, session_statuses
from baton.fleet.registry import MissionRow
from baton.v1 import ring_pb2, station_pb2


def test_a_station_that_never_answers_is_said_within_the_deadline(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(operations, "ASK_TIMEOUT_S", 0.5)
    with socket.socket() as silent:  # accepts connections, never speaks
        silent.bind(("127.0.0.1", 0))
        silent.listen()
        port = silent.getsockname()[1]
        config = BatonConfig.model_validate(
            {
                "controllers": [
                    {"id": 1, "address": f"127.0.0.1:{port}"},
                    {"id": 2, "address": "127.0.0.1:1"},
                ],
                "tls": {"insecure": True},
            }
        )
        started = time.monotonic()
        replies = ask_stations(config, [1, 2, 3], None)
        elapsed = time.monotonic() - started
    assert elapsed < 3.0  # at once, each within its own deadline
    assert replies[1] == f"station 1 (127.0.0.1:{port}): no answer: DEADLINE_EXCEEDED: " + (
        "Deadline Exceeded"
    )
    assert (
        isinstance(replies[2], str)
        and "station 2 (127.0.0.1:1): no answer: UNAVAILABLE" in (replies[2])
    )
    assert replies[3] == "station 3: not in the network file; add it with its address"


def test_the_overview_takes_the_master_of_the_newest_epoch_and_the_furthest_request() -> None:
    mission = MissionRow(7, "d1", "admitted", (), (1, 2, 3, 4), 1, 0.0, departed=(4,))

    def hosting(sid: int, **fields: object) -> station_pb2.StationStatus:
        status = ring_pb2.ControllerStatus(id=sid, **fields)  # type: ignore[arg-type]
        session = station_pb2.StationMission(
            mission_id="7", state=station_pb2.SESSION_STATE_HOSTING, status=status
        )
        return station_pb2.StationStatus(id=sid, missions=[session])

    running = ring_pb2.MISSION_STATE_RUNNING
    replies: dict[int, station_pb2.StationStatus | str] = {
        # Station 1 still says master in epoch 1; station 2 was granted epoch 2.
        1: hosting(1, master=True, epoch=1, reqnr=9, mission=running),
        2: hosting(2, master=True, epoch=2, reqnr=12, mission=ring_pb2.MISSION_STATE_DONE),
        3: "station 3 (127.0.0.1:9): no answer: UNAVAILABLE: down",
    }
    sessions = session_statuses(mission, replies)
    assert sorted(sessions) == [1, 2, 3]  # 4 left the ring
    seen = overview(sessions)
    assert (seen.master, seen.state, seen.reqnr) == (2, "done", 12)
    assert seen.silent == ("station 3 (127.0.0.1:9): no answer: UNAVAILABLE: down",)
    assert overview({3: "silent"}) == operations.Overview(None, "unknown", 0, ("silent",))
