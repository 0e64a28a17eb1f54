"""MAVLink 2 signing between the drone service and its autopilot (docs/design.md, Security).

The pure part (``baton.signing``) is checked against pymavlink's own
implementation of the rule; the relay and the sim vehicle as real processes:
a drone with the vehicle's key flies it, a ground station without the key
cannot command it (counted where it would act: the vehicle), and a drone
with the wrong key says so in GetStatus instead of looking like a silent
autopilot.
"""

from __future__ import annotations

import json
import os
import stat
import time
from pathlib import Path

import pytest
from autopilots import SKIP_REASON, Sitl, sitl_binary
from helpers.drone_bed import Controller, drone_bed
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from baton.drone.mavlink_relay import RelayUrlError, VehicleEndpoint
from baton.signing import (
    REFUSED_REASON,
    Signer,
    SigningKeyError,
    read_key,
    timestamp_now,
    write_key,
)
from baton.v1 import drone_api_pb2 as api

KEY = bytes(range(1, 33))
OTHER_KEY = bytes(range(2, 34))


def ground_station(key: bytes | None = None) -> mavlink.MAVLink:
    """A pymavlink encoder as MAVSDK would be (system 245), signing with ``key``."""
    mav = mavlink.MAVLink(None, srcSystem=245, srcComponent=190)
    if key is not None:
        mav.signing.secret_key = key
        mav.signing.timestamp = timestamp_now()
        mav.signing.sign_outgoing = True
    return mav


def autopilot_parser(key: bytes) -> mavlink.MAVLink:
    """pymavlink as an autopilot holding ``key`` checks frames: nothing unsigned."""
    mav = mavlink.MAVLink(None)
    mav.robust_parsing = True
    mav.signing.secret_key = key
    mav.signing.allow_unsigned_callback = lambda _mav, _msg_id: False
    return mav


def arm_frame(mav: mavlink.MAVLink) -> bytes:
    return bytes(
        mav.command_long_encode(
            1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0
        ).pack(mav)
    )


# --- the pure signer --------------------------------------------------------------


def test_a_signed_frame_is_the_same_message_and_passes_pymavlink_check() -> None:
    station = ground_station()
    frames = [arm_frame(station), bytes(station.heartbeat_encode(6, 8, 0, 0, 0).pack(station))]
    signed, dropped = Signer(KEY).sign(b"".join(frames))
    assert dropped == [] and len(signed) == 2
    plain_parser = mavlink.MAVLink(None)
    for frame, original in zip(signed, frames, strict=True):
        (checked,) = autopilot_parser(KEY).parse_buffer(frame)
        (plain,) = plain_parser.parse_buffer(original)
        assert checked.get_signed()
        assert checked.to_dict() == plain.to_dict()
        assert (checked.get_seq(), checked.get_srcSystem(), checked.get_srcComponent()) == (
            plain.get_seq(),
            245,
            190,
        )


def test_the_autopilot_refuses_what_the_relay_did_not_sign_with_its_key() -> None:
    station = ground_station()
    (signed_with_other_key,), _ = Signer(OTHER_KEY).sign(arm_frame(station))
    (signed,), _ = Signer(KEY).sign(arm_frame(station))
    tampered = bytearray(signed)
    tampered[12] ^= 1  # a payload byte (the CRC is fixed up by an attacker, the signature not)
    parser = autopilot_parser(KEY)
    for frame in (arm_frame(station), signed_with_other_key):
        (msg,) = parser.parse_buffer(frame)
        assert msg.get_type() == "BAD_DATA" and msg.reason == REFUSED_REASON
    assert [m.get_type() for m in parser.parse_buffer(signed)] == ["COMMAND_LONG"]
    # The same frame again is a replay: its timestamp is not newer than the stream's.
    assert [m.get_type() for m in parser.parse_buffer(signed)] == ["BAD_DATA"]


def test_only_signed_frames_from_the_autopilot_reach_mavsdk() -> None:
    autopilot = ground_station(KEY)
    forger = ground_station(OTHER_KEY)
    plain = ground_station()
    good = bytes(autopilot.heartbeat_encode(2, 3, 0, 0, 0).pack(autopilot))
    radio = bytes(plain.radio_status_encode(1, 2, 3, 4, 5, 6, 7).pack(plain))
    data = (
        good
        + bytes(plain.heartbeat_encode(2, 3, 0, 0, 0).pack(plain))
        + bytes(forger.heartbeat_encode(2, 3, 0, 0, 0).pack(forger))
        + radio  # a radio modem's, injected unsigned: accepted as ArduPilot does
    )
    signer = Signer(KEY)
    # A TCP link hands over bytes in any pieces.
    accepted, refused = [], []
    for start in range(0, len(data), 7):
        checked = signer.check(data[start : start + 7])
        accepted += checked.accepted
        refused += checked.refused
    assert accepted == [good, radio]
    assert refused == [REFUSED_REASON, REFUSED_REASON]
    assert signer.check(good).refused == [REFUSED_REASON]  # replayed


def test_mavlink_1_cannot_be_signed_and_is_dropped_with_the_reason() -> None:
    station = ground_station()
    v1 = bytes(station.heartbeat_encode(6, 8, 0, 0, 0).pack(station, force_mavlink1=True))
    signed, dropped = Signer(KEY).sign(v1)
    assert signed == [] and dropped == ["MAVLink 1 HEARTBEAT (cannot be signed)"]


def test_key_files(tmp_path: Path) -> None:
    key = write_key(tmp_path / "k")
    assert read_key(tmp_path / "k") == key
    assert stat.S_IMODE(os.stat(tmp_path / "k").st_mode) == 0o600
    with pytest.raises(SigningKeyError, match="exists; remove it first"):
        write_key(tmp_path / "k")
    (tmp_path / "short").write_text("abcd\n")
    (tmp_path / "zeros").write_text("00" * 32)
    for name, why in (
        ("missing", "no such file; make one with `baton certs mavlink-key FILE`"),
        ("short", "not 64 hexadecimal digits"),
        ("zeros", "all zeros turns signing off"),
    ):
        with pytest.raises(SigningKeyError, match=why):
            read_key(tmp_path / name)


def test_the_relay_holds_network_links_and_says_why_not_a_serial_one() -> None:
    assert VehicleEndpoint.parse("udp://0.0.0.0:14540") == VehicleEndpoint(
        "udpin", "0.0.0.0", 14540
    )
    assert VehicleEndpoint.parse("tcp://127.0.0.1:5762").scheme == "tcpout"
    assert VehicleEndpoint.parse("udpout://10.0.0.2:14550").scheme == "udpout"
    with pytest.raises(RelayUrlError, match="not available on a serial link"):
        VehicleEndpoint.parse("serial:///dev/ttyUSB0:57600")
    with pytest.raises(RelayUrlError, match="signing needs one of"):
        VehicleEndpoint.parse("udpin://nohost")


# --- the relay and the sim vehicle as processes ----------------------------------


def refusals_logged(log: Path) -> list[dict[str, object]]:
    lines = [json.loads(line) for line in log.read_text().splitlines() if line.startswith("{")]
    return [line for line in lines if str(line.get("msg", "")).startswith("MAVLink frames refused")]


def test_a_drone_with_the_key_flies_and_a_station_without_it_cannot_command(
    tmp_path: Path,
) -> None:
    key = tmp_path / "mavlink.key"
    write_key(key)
    with drone_bed(tmp_path, None, 10.0, "", vehicle_key=key, drone_key=key) as bed:
        link = bed.status().vehicle
        assert link.signing and link.refused_frames == 0
        c0 = Controller(bed, 0)
        c0.invoke("/baton.v1.Mobility/Arm", api.ArmRequest(), api.ArmReply)
        c0.invoke("/baton.v1.Mobility/Takeoff", api.TakeoffRequest(altitude_m=10), api.TakeoffReply)
        bed.wait_until("10 m up", lambda s: s.position.relative_altitude_m > 9.5)

        # An attacker on the vehicle's link without the key: land and disarm.
        attacker = mavutil.mavlink_connection(
            bed.vehicle_url.replace("udpout://", "udpout:"), source_system=245
        )
        try:
            for command, p1 in (
                (mavlink.MAV_CMD_NAV_LAND, 0),
                (mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0),
            ):
                attacker.mav.command_long_send(1, 1, command, 0, p1, 21196, 0, 0, 0, 0, 0)
            deadline = time.monotonic() + 20
            while not refusals_logged(tmp_path / "sim.log"):
                assert time.monotonic() < deadline, "the vehicle never refused the attacker"
                attacker.mav.heartbeat_send(6, 8, 0, 0, 0)
                time.sleep(0.05)
            # Not acknowledged, not acted on: still armed and flying at 10 m.
            assert attacker.recv_match(type="COMMAND_ACK", blocking=True, timeout=1) is None
        finally:
            attacker.close()
        status = bed.status()
        assert status.flight_state.armed and status.flight_state.in_air
        assert status.position.relative_altitude_m == pytest.approx(10, abs=0.6)

        c0.invoke("/baton.v1.Mobility/Land", api.LandRequest(), api.LandReply)
        bed.wait_until("landed", lambda s: not s.flight_state.in_air, 60)
        assert bed.status().vehicle.refused_frames == 0


def test_a_drone_with_the_wrong_key_says_why_the_autopilot_is_silent(tmp_path: Path) -> None:
    write_key(tmp_path / "vehicle.key")
    write_key(tmp_path / "drone.key")
    with drone_bed(
        tmp_path,
        None,
        10.0,
        "",
        vehicle_key=tmp_path / "vehicle.key",
        drone_key=tmp_path / "drone.key",
        ready=False,
    ) as bed:
        status = bed.wait_until("frames refused", lambda s: s.vehicle.refused_frames > 0, 30)
        assert not status.vehicle_connected
        assert status.vehicle.last_refusal == REFUSED_REASON
        assert "refused by MAVLink signing" in status.vehicle.problem
        assert "does it hold the drone's key?" in status.vehicle.problem
        # And the vehicle refused the drone's frames too: nothing was acted on.
        deadline = time.monotonic() + 20
        while not refusals_logged(tmp_path / "sim.log"):
            assert time.monotonic() < deadline, "the vehicle never logged the refusal"
            time.sleep(0.05)


@pytest.mark.sitl
def test_ardupilot_holding_the_key_flies_for_the_drone_and_ignores_a_station_without_it(
    tmp_path: Path,
) -> None:
    if sitl_binary() is None:
        pytest.skip(SKIP_REASON)
    key = tmp_path / "mavlink.key"
    write_key(key)
    sitl = Sitl(tmp_path / "sitl", mavlink_key=key)
    (tmp_path / "sitl").mkdir()
    sitl.start(timeout_s=90)  # `baton sitl` checked that SITL answers signed with the key
    try:
        # SERIAL2: a ground station on SITL's network port, first without the key.
        station = mavutil.mavlink_connection(sitl.monitor_url, source_system=250)
        assert station.wait_heartbeat(timeout=30) is not None

        def asks_version() -> object:
            station.mav.command_long_send(
                1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0,
            )  # fmt: skip
            return station.recv_match(type="AUTOPILOT_VERSION", blocking=True, timeout=3)

        assert asks_version() is None, "SITL answered a station without the key"

        with drone_bed(tmp_path, sitl.url, sitl.speedup, "", drone_key=key) as bed:
            assert bed.status().vehicle.signing
            c0 = Controller(bed, 0)
            c0.invoke("/baton.v1.Mobility/Arm", api.ArmRequest(), api.ArmReply)
            c0.invoke(
                "/baton.v1.Mobility/Takeoff", api.TakeoffRequest(altitude_m=10), api.TakeoffReply
            )
            bed.wait_until("10 m up", lambda s: s.position.relative_altitude_m > 9.5, 90)

            # The station without the key orders a landing: not acknowledged,
            # not flown (still 10 m up once the drone's telemetry is newer).
            station.mav.command_long_send(1, 1, mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, 0, 0, 0, 0, 0)
            assert station.recv_match(type="COMMAND_ACK", blocking=True, timeout=3) is None
            status = bed.status()
            assert status.flight_state.in_air
            assert status.position.relative_altitude_m == pytest.approx(10, abs=1.0)

            # The same station with the key is answered: the silence above was the key.
            station.setup_signing(read_key(key), sign_outgoing=True)
            assert asks_version() is not None

            c0.invoke("/baton.v1.Mobility/Land", api.LandRequest(), api.LandReply)
            bed.wait_until("landed", lambda s: not s.flight_state.in_air, 120)
            assert bed.status().vehicle.refused_frames == 0
        station.close()
    finally:
        sitl.stop()
