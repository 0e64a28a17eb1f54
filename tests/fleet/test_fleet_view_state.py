"""The live fleet view's document (pure: baton.view.state) and its web server's routes
(baton.view.server, over a real socket, fed a scripted read)."""

from __future__ import annotations

import asyncio
import json
from typing import Any

import pytest
from waiting import eventually

from baton.drone.policy import Station
from baton.fleet.registry import MissionRow, NamedStation
from baton.sdk.geo import offset
from baton.sdk.types import Position
from baton.v1 import drone_api_pb2, drone_pb2, ring_pb2, station_pb2
from baton.view.server import FleetViewServer
from baton.view.state import VIEW_FORMAT, changed, fleet_view

HOME = Position(47.397742, 8.545594)
STATIONS = [
    NamedStation("s2", Station(2, offset(HOME, 0, 500), 400.0)),
    NamedStation("s1", Station(1, HOME, 400.0)),
    NamedStation("s3", Station(3, offset(HOME, 0, 1000), 400.0), drained=True),
]
ALPHA = MissionRow(7, "alpha", "admitted", (HOME, offset(HOME, 0, 900)), (1, 2), 1, 0.0, "x:1")
GONE = MissionRow(3, "gone", "cancelled", (HOME,), (1,), 1, 0.0)


def hosting(sid: int, master: bool, epoch: int, reqnr: int) -> station_pb2.StationStatus:
    status = ring_pb2.ControllerStatus(
        id=sid, master=master, epoch=epoch, reqnr=reqnr, mission=ring_pb2.MISSION_STATE_RUNNING
    )
    return station_pb2.StationStatus(
        id=sid,
        missions=[
            station_pb2.StationMission(
                mission_id="7", state=station_pb2.SESSION_STATE_HOSTING, status=status
            )
        ],
    )


def drone_at(north_m: float, east_m: float, master: int, epoch: int) -> drone_pb2.DroneStatus:
    here = offset(HOME, north_m, east_m)
    return drone_pb2.DroneStatus(
        master=master,
        epoch=epoch,
        position=drone_api_pb2.Position(
            latitude_deg=here.latitude_deg, longitude_deg=here.longitude_deg
        ),
    )


def test_stations_and_drones_are_placed_in_metres_of_the_first_station() -> None:
    replies: dict[int, station_pb2.StationStatus | str] = {
        1: hosting(1, False, 1, 12),
        2: hosting(2, True, 2, 14),
        3: "station 3 (127.0.0.1:9): no answer: UNAVAILABLE: down",
    }
    view = fleet_view(STATIONS, [ALPHA, GONE], replies, {7: drone_at(30, 420, 2, 2)}, 100.0)
    assert view["format"] == VIEW_FORMAT
    assert [s["id"] for s in view["stations"]] == [1, 2, 3]
    one, two, three = view["stations"]
    assert (one["east_m"], one["north_m"]) == (0.0, 0.0)
    assert two["east_m"] == pytest.approx(500, abs=0.1) and two["missions"] == ["7"]
    assert three["drained"] and not three["answering"] and three["missions"] == []
    # Only missions in flight are drawn; the cancelled one is not.
    (alpha,) = view["drones"]
    assert alpha["drone"] == "alpha" and alpha["ring"] == [1, 2]
    assert alpha["place"] == {"east_m": pytest.approx(420, abs=0.1), "north_m": 30.0}
    assert (alpha["master"], alpha["state"], alpha["reqnr"]) == (2, "running", 14)
    assert alpha["colour"] == two["colour"]  # a drone in its master's colour
    assert view["problems"] == ["station 3 (127.0.0.1:9): no answer: UNAVAILABLE: down"]
    west, south, east, north = view["bounds"]
    assert west < -400 and east > 1400 and south < -400 and north > 400
    json.dumps(view)  # what the server sends


def test_a_silent_drone_is_drawn_with_the_sessions_master_and_said() -> None:
    replies = {1: hosting(1, True, 3, 20), 2: hosting(2, True, 2, 19)}
    view = fleet_view(STATIONS, [ALPHA], replies, {7: "drone (x:1): no answer"}, 1.0)
    (alpha,) = view["drones"]
    # The newest epoch's master, and no place: the drone did not say where it is.
    assert alpha["master"] == 1 and alpha["place"] is None and not alpha["answering"]
    assert "mission 7 (alpha): drone (x:1): no answer" in view["problems"]


def test_a_silent_station_and_an_unknown_position_leave_the_drone_listed() -> None:
    replies: dict[int, station_pb2.StationStatus | str] = {1: "station 1: no answer", 2: "s2: no"}
    view = fleet_view(STATIONS, [ALPHA], replies, {7: drone_at(0, 0, 1, 1)}, 1.0)
    (alpha,) = view["drones"]
    assert alpha["state"] == "unknown" and alpha["master"] == 1
    view = fleet_view(STATIONS, [ALPHA], replies, {7: drone_pb2.DroneStatus(master=1)}, 1.0)
    assert view["drones"][0]["place"] is None  # all zero: not known yet


def test_only_a_change_in_what_is_shown_is_sent() -> None:
    replies = {1: hosting(1, True, 1, 5)}
    first = fleet_view(STATIONS, [ALPHA], replies, {7: drone_at(0, 10, 1, 1)}, 1.0)
    again = fleet_view(STATIONS, [ALPHA], replies, {7: drone_at(0, 10, 1, 1)}, 2.0)
    moved = fleet_view(STATIONS, [ALPHA], replies, {7: drone_at(0, 20, 1, 1)}, 3.0)
    assert changed(None, first) and not changed(first, again) and changed(again, moved)


async def _get(address: str, path: str, method: str = "GET") -> tuple[str, bytes]:
    host, _, port = address.rpartition(":")
    reader, writer = await asyncio.open_connection(host, int(port))
    writer.write(f"{method} {path} HTTP/1.1\r\nHost: {address}\r\n\r\n".encode())
    await writer.drain()
    answer = await reader.read()
    writer.close()
    head, _, body = answer.partition(b"\r\n\r\n")
    return head.decode(), body


async def test_the_server_serves_the_page_the_document_and_its_changes_as_events() -> None:
    documents: list[dict[str, Any]] = [{"format": VIEW_FORMAT, "at": 0, "n": 0}]
    failures = ["the registry is locked"]

    def read() -> dict[str, Any]:
        if failures:  # a failed read is said and tried again
            raise RuntimeError(failures.pop())
        return documents[-1]

    server = FleetViewServer(read, poll_s=0.01)
    address = await server.start("127.0.0.1", 0)
    try:
        head, page = await _get(address, "/")
        assert head.startswith("HTTP/1.1 200") and "connect-src 'self'" in head
        # It loads nothing (no src, no link, no import) but its own server's events.
        assert b'new EventSource("events")' in page
        assert not any(word in page for word in (b"src=", b"<link", b"import", b"url("))
        head, body = await _get(address, "/state")
        assert json.loads(body)["n"] == 0
        head, body = await _get(address, "/nowhere")
        assert head.startswith("HTTP/1.1 404") and b"there is /, /state, /events" in body
        head, body = await _get(address, "/", "POST")
        assert head.startswith("HTTP/1.1 405")

        host, _, port = address.rpartition(":")
        reader, writer = await asyncio.open_connection(host, int(port))
        writer.write(b"GET /events HTTP/1.1\r\n\r\n")
        await writer.drain()
        head_bytes = await reader.readuntil(b"\r\n\r\n")
        assert b"text/event-stream" in head_bytes

        async def event() -> dict[str, Any]:
            line = await reader.readuntil(b"\n\n")
            assert line.startswith(b"data: ")
            parsed: dict[str, Any] = json.loads(line[6:])
            return parsed

        assert (await event())["n"] == 0
        # Same content, newer time: not sent; a change: sent.
        documents.append({"format": VIEW_FORMAT, "at": 1, "n": 0})
        documents.append({"format": VIEW_FORMAT, "at": 2, "n": 1})
        assert (await asyncio.wait_for(event(), 5))["n"] == 1
        await eventually(lambda: server.document is not None and server.document["at"] == 2, "2")
    finally:
        await server.stop()
    assert not server._handlers  # the open event stream was ended with the server
    writer.close()
