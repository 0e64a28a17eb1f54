"""A station's pure decisions (station/rules.py) and its port's refusals, in process."""

from __future__ import annotations

import json
from pathlib import Path

import grpc
import pytest

from baton.config import TlsConfig
from baton.rpc.channels import aio_channel
from baton.rpc.errors import StatusError
from baton.rpc.mission import mission_metadata
from baton.station.app import StationApp
from baton.station.rules import mission_config, route
from baton.v1 import ring_pb2, ring_pb2_grpc, station_pb2, station_pb2_grpc

INSECURE = TlsConfig(insecure=True)
ONE = [{"id": 1, "address": "127.0.0.1:7001"}]
CONFIG = {"controllers": [*ONE, {"id": 2, "address": "127.0.0.1:7002"}], "ring": [1, 2]}


def test_a_call_goes_to_the_session_it_names_and_to_no_other() -> None:
    sessions = {"alpha": "A", "bravo": "B"}
    assert route(sessions, "bravo", 2, "/baton.v1.ControllerRing/LogRing") == "B"
    unknown = route(sessions, "charlie", 2, "/baton.v1.ControllerRing/GetStatus")
    assert isinstance(unknown, StatusError)
    assert unknown.code == grpc.StatusCode.NOT_FOUND
    assert "'charlie'" in unknown.message and "alpha, bravo" in unknown.message
    unnamed = route(sessions, None, 2, "/baton.v1.ControllerRing/GetStatus")
    assert isinstance(unnamed, StatusError)
    assert unnamed.code == grpc.StatusCode.INVALID_ARGUMENT
    assert "baton-mission" in unnamed.message


@pytest.mark.parametrize("named", ["../alpha", "", "a" * 65, "x" * 8000])
def test_a_call_naming_what_is_not_a_mission_id_is_invalid_and_says_so_briefly(
    named: str,
) -> None:
    refused = route({"alpha": "A"}, named, 2, "/baton.v1.ControllerRing/LogRing")
    assert isinstance(refused, StatusError)
    assert refused.code == grpc.StatusCode.INVALID_ARGUMENT
    assert refused.message.startswith("LogRing: the baton-mission metadata ")
    assert "is not a mission id" in refused.message and "hosts: alpha" in refused.message
    assert len(refused.message) < 400  # a value kilobytes long is not echoed whole


@pytest.mark.parametrize(
    ("mission", "config", "program", "code", "named"),
    [
        ("al pha", CONFIG, "m.py", grpc.StatusCode.INVALID_ARGUMENT, "mission_id"),
        ("-x", CONFIG, "m.py", grpc.StatusCode.INVALID_ARGUMENT, "mission_id"),
        ("hosted", CONFIG, "m.py", grpc.StatusCode.ALREADY_EXISTS, "hosted"),
        ("alpha", CONFIG, "", grpc.StatusCode.INVALID_ARGUMENT, "program"),
        ("alpha", "{", "m.py", grpc.StatusCode.INVALID_ARGUMENT, "config: not valid"),
        ("alpha", {"ring": [1]}, "m.py", grpc.StatusCode.INVALID_ARGUMENT, "controllers"),
        (
            "alpha",
            {**CONFIG, "flush_limit": "lots"},
            "m.py",
            grpc.StatusCode.INVALID_ARGUMENT,
            "flush_limit",
        ),
        (
            "alpha",
            {"controllers": ONE, "ring": [1]},
            "m.py",
            grpc.StatusCode.FAILED_PRECONDITION,
            "does not hold station 2",
        ),
    ],
)
def test_a_mission_that_may_not_start_is_refused_naming_the_field(
    mission: str, config: object, program: str, code: grpc.StatusCode, named: str
) -> None:
    text = config if isinstance(config, str) else json.dumps(config)
    refused = mission_config(mission, text, program, 2, {"hosted": None}, INSECURE)
    assert isinstance(refused, StatusError)
    assert refused.code == code
    assert named in refused.message


def test_a_session_runs_with_the_stations_tls_and_its_own_mission_id() -> None:
    given = {**CONFIG, "tls": {"certs": "/elsewhere"}, "mission_id": "other"}
    mine = TlsConfig(certs=Path("/station/certs"))
    config = mission_config("alpha", json.dumps(given), "m.py", 2, {}, mine)
    assert not isinstance(config, StatusError)
    assert config.tls == mine
    assert config.mission_id == "alpha"


async def test_the_stations_port_refuses_unknown_missions_and_bad_starts(tmp_path: Path) -> None:
    app = StationApp(2, "127.0.0.1:0", INSECURE, tmp_path / "state")
    await app.start()
    try:
        async with aio_channel(app.server.address) as channel:
            ring: ring_pb2_grpc.ControllerRingAsyncStub = ring_pb2_grpc.ControllerRingStub(channel)
            with pytest.raises(grpc.aio.AioRpcError) as unknown:
                await ring.GetStatus(
                    ring_pb2.GetControllerStatusRequest(), metadata=mission_metadata("nope")
                )
            assert unknown.value.code() == grpc.StatusCode.NOT_FOUND
            assert "'nope'" in (unknown.value.details() or "")
            stream = ring.LogRing(metadata=mission_metadata("nope"))
            with pytest.raises(grpc.aio.AioRpcError) as streamed:
                await stream.read()
            assert streamed.value.code() == grpc.StatusCode.NOT_FOUND
            with pytest.raises(grpc.aio.AioRpcError) as unnamed:
                await ring.GetStatus(ring_pb2.GetControllerStatusRequest())
            assert unnamed.value.code() == grpc.StatusCode.INVALID_ARGUMENT

            station: station_pb2_grpc.StationAsyncStub = station_pb2_grpc.StationStub(channel)
            with pytest.raises(grpc.aio.AioRpcError) as missing:
                await station.StartMission(
                    station_pb2.StartMissionRequest(
                        mission_id="alpha",
                        config=json.dumps(CONFIG),
                        program=str(tmp_path / "absent.py"),
                    )
                )
            assert missing.value.code() == grpc.StatusCode.INVALID_ARGUMENT
            assert "absent.py" in (missing.value.details() or "")
            with pytest.raises(grpc.aio.AioRpcError) as stop_unknown:
                await station.StopMission(station_pb2.StopMissionRequest(mission_id="alpha"))
            assert stop_unknown.value.code() == grpc.StatusCode.NOT_FOUND
            status = await station.GetStation(station_pb2.GetStationRequest())
            assert status.id == 2 and not status.missions
        assert not (tmp_path / "state" / "missions" / "alpha").exists()
    finally:
        await app.stop()
