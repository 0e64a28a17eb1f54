"""A ground station watches live (issue 32, item 5), across real processes.

The drone forwards the autopilot's MAVLink to the GCS endpoints it is given
(``drone.gcs``), so a pymavlink ground station (as QGroundControl or MAVProxy
would) sees the vehicle through a whole testbed flight with handovers. Its
commands are refused by default (watch only: a COMMAND_ACK DENIED, and the
vehicle acts on nothing it sent, by the vehicle's own effects file), or, with
``gcs_override``, taken as an operator override that pauses the mission: the
master's next call waits at the drone until an operator resumes or ends it.

On ArduPilot SITL (where ``BATON_SITL_BINARY`` points at a build; helpers/vehicles.py)
the positions are ArduPilot's own, and the witness of what the vehicle acted on is its
own flight mode in the drone's telemetry log: LAND once (the mission's) watching; LAND
after the station's with override.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from helpers.missions import FAST_LINK
from helpers.vehicles import VEHICLES, Tlog, on_vehicle, skip_without_sitl
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink2
from waiting import eventually

from baton.drone.gcs import GcsEndpoint, GcsEndpointError, GcsLink
from baton.effects import read_effects
from baton.signing import enable, write_key
from baton.testbed.local import (
    VEHICLE_EFFECTS_FILE,
    LocalTestbed,
    MissionPlan,
    TestbedPlan,
    free_port,
    local_config,
)
from baton.v1 import drone_pb2, ring_pb2

mavlink = mavutil.mavlink
MISSION = MissionPlan(grid=3, spacing_m=20.0, altitude_m=5.0, speed_m_s=5.0, poll_s=1.0)
STATION_SYSTEM = 255  # the pymavlink ground station's MAVLink system id


class Station:
    """A pymavlink ground station listening where the drone forwards (udpin), in a thread;
    with ``key``, it signs what it sends and accepts only signed frames."""

    def __init__(self, key: bytes | None = None) -> None:
        self.port = free_port()
        self.link = mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{self.port}", source_system=STATION_SYSTEM
        )
        self.key = key
        if key is not None:
            enable(self.link.mav, key, sign_outgoing=True)
        self.signed_acks = 0
        self.positions: list[float] = []  # arrival times of GLOBAL_POSITION_INT
        self.acks: list[Any] = []
        self.texts: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._listen, daemon=True)
        self._thread.start()

    def _listen(self) -> None:
        while not self._stop.is_set():
            msg = self.link.recv_match(blocking=True, timeout=0.2)
            if msg is None:
                continue
            kind = msg.get_type()
            if kind == "GLOBAL_POSITION_INT":
                self.positions.append(time.monotonic())
            elif kind == "COMMAND_ACK" and msg.target_system == 255:
                self.acks.append(msg)  # to this station (the autopilot's to MAVSDK pass too)
                self.signed_acks += bool(msg.get_msgbuf()[2] & 0x01)
            elif kind == "STATUSTEXT":
                self.texts.append(msg.text)

    def land(self) -> None:
        if self.key is not None:  # mavutil made a new MAVLink 2 object on the first frame
            enable(self.link.mav, self.key, sign_outgoing=True)
        self.link.mav.command_long_send(1, 1, mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, 0, 0, 0, 0, 0)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.link.close()


def plan(
    station: Station, override: bool, key_file: Path | None = None, vehicle: str = "sim"
) -> TestbedPlan:
    config = local_config(3, flush_limit=0, speedup=10.0, drone_link=FAST_LINK)
    drone = config.drone.model_copy(
        update={
            "gcs": [f"udp:127.0.0.1:{station.port}"],
            "gcs_override": override,
            "mavlink_key": key_file,
        }
    )
    config = config.model_copy(update={"drone": drone})
    sim = TestbedPlan(config=config, handovers=((20, 1), (45, 2)), mission=MISSION)
    return on_vehicle(sim, vehicle)


def test_a_gcs_endpoint_is_checked() -> None:
    assert GcsEndpoint.parse("udp:127.0.0.1:14550") == GcsEndpoint("127.0.0.1", 14550)
    assert GcsEndpoint.parse("udp://10.0.0.2:14551") == GcsEndpoint("10.0.0.2", 14551)
    for bad in ("tcp:127.0.0.1:5760", "udp:14550", "udp:host:99999"):
        try:
            GcsEndpoint.parse(bad)
        except GcsEndpointError as exc:
            assert repr(bad) in str(exc) and "udp:" in str(exc)
        else:
            raise AssertionError(f"{bad} accepted")


@pytest.mark.parametrize("vehicle", VEHICLES)
async def test_a_ground_station_watches_a_whole_flight_and_its_land_is_refused(
    vehicle: str, tmp_path: Path
) -> None:
    skip_without_sitl(vehicle)
    station = Station()
    try:
        bed = plan(station, override=False, vehicle=vehicle)
        async with LocalTestbed(bed, tmp_path) as testbed:

            async def airborne() -> bool:
                return (await testbed.snapshot(audit=False)).drone.last_reqnr >= 10

            await eventually(airborne, "the vehicle flying", 60)
            station.land()
            await eventually(lambda: station.acks, "the drone's COMMAND_ACK", 10)
            snapshot = await testbed.run_mission(240)
    finally:
        station.close()
    [ack] = station.acks
    assert (ack.command, ack.result) == (mavlink.MAV_CMD_NAV_LAND, mavlink.MAV_RESULT_DENIED)
    assert any(t.startswith("baton in control, master ") for t in station.texts), station.texts
    assert any(t.endswith("; GCS watch only") for t in station.texts)
    # Watch only, by the vehicle's own count: the mission's one land, none of the station's.
    if vehicle == "sim":
        effects = read_effects(tmp_path / VEHICLE_EFFECTS_FILE) or []
        assert [e["effect"] for e in effects].count("land") == 1
    else:  # ArduCopter entered LAND once, and heard no command of the station's system
        tlog = Tlog(tmp_path)
        assert len(tlog.entered("LAND")) == 1, tlog.entered("LAND")
        assert [c for c in tlog.sent() if c.system == STATION_SYSTEM] == []
    assert all(c.mission == ring_pb2.MISSION_STATE_DONE for c in snapshot.controllers.values())
    assert [h.new_master for h in snapshot.drone.handovers] == [1, 2]
    # Positions at 1 Hz or more through the whole flight, handovers included.
    gaps = [b - a for a, b in zip(station.positions, station.positions[1:], strict=False)]
    assert len(station.positions) > 20 and max(gaps) < 1.0, max(gaps)


@pytest.mark.parametrize("vehicle", VEHICLES)
async def test_with_override_a_ground_stations_land_pauses_the_mission(
    vehicle: str, tmp_path: Path
) -> None:
    skip_without_sitl(vehicle)
    station = Station()
    tlog = Tlog(tmp_path)
    try:
        bed = plan(station, override=True, vehicle=vehicle)
        async with LocalTestbed(bed, tmp_path) as testbed:

            async def airborne() -> bool:
                return (await testbed.snapshot(audit=False)).drone.last_reqnr >= 10

            await eventually(airborne, "the vehicle flying", 60)
            asked_at = time.time()
            station.land()

            def landed_by_station() -> bool:
                if vehicle == "sitl":  # ArduCopter's own word: LAND, after the station's
                    return tlog.first_mode("LAND", after=asked_at) is not None
                effects = read_effects(tmp_path / VEHICLE_EFFECTS_FILE) or []
                return "land" in [e["effect"] for e in effects]

            await eventually(landed_by_station, "the vehicle acting on the station's LAND", 20)
            stub = testbed.drone_stub
            assert stub is not None

            async def paused() -> drone_pb2.OperatorCommand | None:
                status = await stub.GetStatus(drone_pb2.GetDroneStatusRequest())
                return status.paused if status.HasField("paused") else None

            pause = await eventually(paused, "the mission paused by the station", 20)
            drone_log = tmp_path / "logs" / "drone.log"
            await eventually(
                lambda: "request waits: the mission is paused" in drone_log.read_text(),
                "the master's next call waiting at the drone",
                20,
            )
            status = await stub.GetStatus(drone_pb2.GetDroneStatusRequest())
            # The operator ends the mission the station took over: every program is told.
            await stub.LandNow(drone_pb2.LandNowRequest(note="the station landed it"))

            async def ended() -> list[str]:
                snapshot = await testbed.snapshot(audit=False)
                errors = [c.mission_error for c in snapshot.controllers.values()]
                return errors if all(errors) else []

            errors = await eventually(ended, "every program ended by the land-now", 60)
    finally:
        station.close()
    assert (pause.by, pause.action) == (f"ground station {STATION_SYSTEM}", "")  # it flies it
    assert "MAV_CMD_NAV_LAND" in pause.reason
    assert status.last_reqnr == pause.after_reqnr  # nothing admitted while paused
    assert all("the mission has ended (told to land now by the operator" in e for e in errors)


async def test_with_signing_the_ground_station_link_is_signed(tmp_path: Path) -> None:
    """drone.mavlink_key: a station holding the key sees the autopilot's signed frames and
    gets the drone's answer signed; pymavlink's station accepts only signed frames."""
    key_file = tmp_path / "mavlink.key"
    key = write_key(key_file)
    station = Station(key)
    try:
        async with LocalTestbed(plan(station, False, key_file), tmp_path) as testbed:

            async def airborne() -> bool:
                return (await testbed.snapshot(audit=False)).drone.last_reqnr >= 10

            await eventually(airborne, "the vehicle flying", 60)
            station.land()
            await eventually(lambda: station.acks, "the drone's signed COMMAND_ACK", 10)
    finally:
        station.close()
    assert station.positions and station.signed_acks == len(station.acks) == 1
    assert station.acks[0].result == mavlink.MAV_RESULT_DENIED


def test_a_bad_gcs_option_names_it_and_the_fix() -> None:
    for program in ("drone", "testbed"):
        result = subprocess.run(
            [sys.executable, "-m", "baton.cli", program, "--gcs", "tcp:127.0.0.1:5760"],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert result.returncode == 2, result.stderr
        assert "--gcs tcp:127.0.0.1:5760: GCS endpoint 'tcp:127.0.0.1:5760': expected " in (
            result.stderr
        )
        assert "udp:HOST:PORT, e.g. udp:127.0.0.1:14550" in result.stderr


# MAV_CMD_REQUEST_OPERATOR_CONTROL (development.xml): not in pymavlink's common
# dialect, so it comes as a bare COMMAND_LONG number.
REQUEST_OPERATOR_CONTROL = 32100


class _Sent:
    """A station's socket, as the drone writes to it: the frames, parsed back."""

    def __init__(self) -> None:
        self.frames: list[Any] = []
        self._parser = mavlink2.MAVLink(None)

    def sendto(self, frame: bytes, addr: object = None) -> None:
        self.frames.extend(self._parser.parse_buffer(frame) or [])


def _request_control(station_system: int = 255) -> bytes:
    """A ground station asking for control of the vehicle (system 1)."""
    out = mavlink2.MAVLink(None, srcSystem=station_system, srcComponent=190)
    request = out.command_long_encode(1, 1, REQUEST_OPERATOR_CONTROL, 0, 0, 0, 0, 0, 0, 0, 0)
    return bytes(request.pack(out))


def test_a_request_for_control_is_denied_watching_and_an_override_with_override() -> None:
    """A station's MAV_CMD_REQUEST_OPERATOR_CONTROL follows the rule of every command:
    watch only, a COMMAND_ACK DENIED naming that command, a status text saying who
    controls the vehicle, and nothing to the autopilot; with override, the request
    is the operator taking over (the mission pauses) and goes on to the autopilot."""
    watching = GcsLink([])
    watching.controller = lambda: "2"
    to_vehicle: list[bytes] = []
    watching.to_vehicle = to_vehicle.append
    sent = _Sent()
    watching.received(_request_control(), sent)  # type: ignore[arg-type]
    [ack, text] = sent.frames
    assert ack.get_type() == "COMMAND_ACK" and ack.command == REQUEST_OPERATOR_CONTROL
    assert ack.result == mavlink2.MAV_RESULT_DENIED and ack.target_system == 255
    assert text.get_type() == "STATUSTEXT" and "master 2; GCS watch only" in text.text
    assert (watching.denied, watching.overrides, to_vehicle) == (1, 0, [])

    overriding = GcsLink([], override=True)
    paused: list[tuple[str, str]] = []
    overriding.on_override = lambda station, what: paused.append((station, what))
    overriding.to_vehicle = to_vehicle.append
    sent = _Sent()
    overriding.received(_request_control(), sent)  # type: ignore[arg-type]
    assert paused == [("ground station 255", "COMMAND_LONG")] and sent.frames == []
    assert len(to_vehicle) == 1 and overriding.overrides == 1
