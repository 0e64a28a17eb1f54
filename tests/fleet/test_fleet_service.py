"""The Fleet service's corners: each failure of the fleet's operations mapped to the
status a gRPC caller expects; the requests it refuses before any station is asked,
served in this process (insecure, no network file); and what a failed start leaves of
an admission."""

from __future__ import annotations

from collections.abc import AsyncIterator, Awaitable
from pathlib import Path

import grpc
import pytest
from helpers.drone_calls import refused_details

from baton.config import ConfigError
from baton.drone.policy import Station
from baton.fleet.admission import Refusal, Refused, admit_mission
from baton.fleet.registry import Malformed, NotInFlight, RegistryError, Taken, Unknown
from baton.fleet.routes import RouteError
from baton.fleet.service import fleet_server, refusal_status, status_of
from baton.fleet.sessions import SessionError
from baton.rpc.channels import aio_channel
from baton.sdk.types import Position
from baton.v1 import fleet_pb2, fleet_pb2_grpc

SURVEY = Path(__file__).parents[2] / "examples" / "survey.plan"
TAKE_OFF = Position(47.397742, 8.545594)
STATION = Station(1, Position(47.398191, 8.545594), 500)
Code = grpc.StatusCode
# A waypoint file without its item 0, the planned home.
BARE_PLAN = "QGC WPL 110\n1\t0\t3\t16\t0\t0\t0\t0\t47.3980\t8.5460\t10\t1\n"


@pytest.mark.parametrize(
    ("error", "code"),
    [
        (Unknown("mission 4: no such mission"), Code.NOT_FOUND),
        (Taken("id 1 is taken by station s1 (id 1)"), Code.ALREADY_EXISTS),
        (Malformed("range_m: 0.0: must be > 0"), Code.INVALID_ARGUMENT),
        (RouteError("plan", "no mission.items list"), Code.INVALID_ARGUMENT),
        (NotInFlight("mission 1: already cancelled"), Code.FAILED_PRECONDITION),
        (RegistryError("fleet.sqlite: not a usable registry"), Code.FAILED_PRECONDITION),
        (ConfigError("network.yaml: controllers: no station 3"), Code.FAILED_PRECONDITION),
        (SessionError("not started: station 2: UNAVAILABLE"), Code.UNAVAILABLE),
        (SessionError("station 2: DEADLINE_EXCEEDED", Code.DEADLINE_EXCEEDED), Code.UNAVAILABLE),
        (SessionError("station 1: program: no file", Code.INVALID_ARGUMENT), Code.INVALID_ARGUMENT),
        (SessionError("station 1: its ring", Code.FAILED_PRECONDITION), Code.FAILED_PRECONDITION),
    ],
)
def test_each_failure_kind_has_its_status_and_keeps_its_message(
    error: Exception, code: grpc.StatusCode
) -> None:
    status = status_of(error)
    assert status is not None and status.code == code
    assert status.message == str(error)


def test_a_failure_that_is_no_request_s_fault_is_not_mapped() -> None:
    assert status_of(KeyError("a bug")) is None


def test_each_refusal_of_admission_has_its_status_naming_the_field() -> None:
    far = Position(47.397742, 8.59)
    cases = {
        Refusal.MALFORMED: admit_mission("d1", [TAKE_OFF, Position(91, 8)], [STATION], {}),
        Refusal.BUSY: admit_mission("d1", [TAKE_OFF], [STATION], {"d1": 7}),
        Refusal.UNCOVERED: admit_mission("d1", [TAKE_OFF, far], [STATION], {}),
        Refusal.NO_STATIONS: admit_mission("d1", [TAKE_OFF], [], {}),
    }
    expected = {
        Refusal.MALFORMED: (Code.INVALID_ARGUMENT, "refused: route[1].latitude_deg: 91"),
        Refusal.BUSY: (Code.ALREADY_EXISTS, "refused: drone: 'd1' already flies mission 7"),
        Refusal.UNCOVERED: (Code.FAILED_PRECONDITION, "refused: route: a stretch no station"),
        Refusal.NO_STATIONS: (Code.FAILED_PRECONDITION, "refused: stations: none registered"),
    }
    for kind, refused in cases.items():
        assert isinstance(refused, Refused) and refused.kind == kind
        status = refusal_status(refused)
        code, start = expected[kind]
        assert status.code == code and status.message.startswith(start), status


@pytest.fixture
async def fleet(tmp_path: Path) -> AsyncIterator[fleet_pb2_grpc.FleetAsyncStub]:
    """A Fleet service in this process, insecure, without a network file, over a
    registry of one station."""
    server = fleet_server(tmp_path / "fleet.sqlite", None, None, "127.0.0.1:0")
    await server.start()
    async with aio_channel(server.address) as channel:
        stub: fleet_pb2_grpc.FleetAsyncStub = fleet_pb2_grpc.FleetStub(channel)  # type: ignore[no-untyped-call]
        location = fleet_pb2.Place(latitude_deg=47.398191, longitude_deg=8.545594)
        await stub.AddStation(
            fleet_pb2.AddStationRequest(name="s1", id=1, location=location, range_m=500)
        )
        yield stub
    await server.stop(0)


async def test_requests_refused_before_any_station_is_asked_name_the_field(
    fleet: fleet_pb2_grpc.FleetAsyncStub,
) -> None:
    place = fleet_pb2.Place(latitude_deg=47.398191, longitude_deg=8.545594)
    take_off = fleet_pb2.Place(latitude_deg=TAKE_OFF.latitude_deg, longitude_deg=8.545594)
    cases: list[tuple[Awaitable[object], grpc.StatusCode, str]] = [
        (fleet.AddStation(fleet_pb2.AddStationRequest(name="s2", id=2, range_m=5)),
         Code.INVALID_ARGUMENT, "location: missing"),
        (fleet.AddStation(fleet_pb2.AddStationRequest(name="s2", id=1, location=place, range_m=5)),
         Code.ALREADY_EXISTS, "id 1 is taken by station s1"),
        (fleet.AddStation(fleet_pb2.AddStationRequest(name="s2", id=2, location=place)),
         Code.INVALID_ARGUMENT, "range_m: 0.0: must be > 0"),
        (fleet.Admit(fleet_pb2.AdmitRequest(drone="d1")),
         Code.INVALID_ARGUMENT, "route: empty"),
        (fleet.Admit(fleet_pb2.AdmitRequest(drone="d1", route=[take_off], home=take_off)),
         Code.INVALID_ARGUMENT, "home: only with a plan"),
        (fleet.Admit(fleet_pb2.AdmitRequest(drone="d1", route=[take_off], program="grid.py")),
         Code.INVALID_ARGUMENT, "program: only with start"),
        (fleet.Admit(fleet_pb2.AdmitRequest(drone="d1", route=[take_off], start=True)),
         Code.INVALID_ARGUMENT, "program: missing"),
        (fleet.Admit(fleet_pb2.AdmitRequest(
            drone="d1", route=[take_off], start=True, program="g", drone_address="d1")),
         Code.INVALID_ARGUMENT, "drone_address: expected host:port like '127.0.0.1:7100'"),
        (fleet.Admit(fleet_pb2.AdmitRequest(drone="d1", route=[take_off], start=True, program="g")),
         Code.FAILED_PRECONDITION, "start: this fleet service has no network file"),
        (fleet.Admit(fleet_pb2.AdmitRequest(drone="d1", plan=BARE_PLAN)),
         Code.INVALID_ARGUMENT, "home: missing: the plan sent has no planned home position"),
        (fleet.Admit(fleet_pb2.AdmitRequest(drone="d1", plan="{}")),
         Code.INVALID_ARGUMENT, 'plan: the plan sent: a .plan file has "fileType"'),
        (fleet.GetMission(fleet_pb2.GetMissionRequest(mission_id=1)),
         Code.FAILED_PRECONDITION, "GetMission: this fleet service has no network file"),
        (fleet.CancelMission(fleet_pb2.CancelMissionRequest(mission_id=9)),
         Code.NOT_FOUND, "mission 9: no such mission"),
        (fleet.DrainStation(fleet_pb2.DrainStationRequest()),
         Code.INVALID_ARGUMENT, "station: missing"),
    ]  # fmt: skip
    for call, code, message in cases:
        assert message in await refused_details(call, code), (code, message)
    # Nothing of a refused admission is kept: the drone is free, the plan's text admitted.
    plan = fleet_pb2.AdmitRequest(drone="d1", plan=SURVEY.read_text())
    admitted = await fleet.Admit(plan)
    assert admitted.mission_id == 1 and [s.id for s in admitted.ring] == [1]
    assert not admitted.started and admitted.mission_config == ""
    listed = await fleet.ListMissions(fleet_pb2.ListMissionsRequest())
    assert [(m.id, m.drone, m.state, m.asked) for m in listed.missions] == [
        (1, "d1", "admitted", False)
    ]
    cancelled = await fleet.CancelMission(fleet_pb2.CancelMissionRequest(mission_id=1))
    assert cancelled.mission.state == "cancelled" and list(cancelled.stopped_on) == []
    cancel = fleet.CancelMission(fleet_pb2.CancelMissionRequest(mission_id=1))
    said = await refused_details(cancel, Code.FAILED_PRECONDITION)
    assert said == "mission 1: already cancelled"


@pytest.mark.parametrize("undone", [True, False])
def test_a_start_that_fails_withdraws_the_admission_unless_a_station_kept_a_session(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, undone: bool
) -> None:
    """Admission that starts: withdrawn when the start was undone everywhere (the drone is
    free, the id not given again); kept for a cancel when a station could not undo it."""
    from baton.config import parse_config
    from baton.fleet import actions
    from baton.fleet.actions import Network, admit_and_start
    from baton.fleet.registry import Registry

    registry = tmp_path / "fleet.sqlite"
    with Registry(registry) as open_registry:
        open_registry.add_station("s1", STATION)
    leftover = () if undone else ("station 1 (127.0.0.1:1): UNAVAILABLE: no answer",)

    def refused_start(*_: object) -> actions.Started:
        raise SessionError("not started: station 2: UNAVAILABLE", Code.UNAVAILABLE, leftover)

    monkeypatch.setattr(actions, "start_mission", refused_start)
    network = Network(
        parse_config({"controllers": [{"id": 1, "address": "127.0.0.1:1"}]}), "n", None
    )
    with pytest.raises(SessionError) as caught:
        admit_and_start(registry, "d1", [TAKE_OFF], network, "grid.py", [])
    with Registry(registry) as open_registry:
        missions = open_registry.missions()
        again = open_registry.admit("d1", [TAKE_OFF])
    if undone:
        assert str(caught.value).startswith("not admitted: not started: station 2")
        assert missions == [] and not isinstance(again, Refused) and again[0] == 2
    else:
        assert "mission 1: not started: station 2" in str(caught.value)
        assert "it stays admitted: cancel it" in str(caught.value)
        assert [m.id for m in missions] == [1] and isinstance(again, Refused)
        assert again.kind == Refusal.BUSY
