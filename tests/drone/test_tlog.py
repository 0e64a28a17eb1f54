"""The drone's telemetry log (drone/tlog.py): packets cut from a stream, read back by pymavlink."""

from __future__ import annotations

import math
import time
from pathlib import Path

from helpers.vehicles import COPTER_MODES, Tlog
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from baton.drone.tlog import MavlinkFramer, TlogWriter, tlog_path, tlog_records
from baton.signing import Signer


def packets() -> list[bytes]:
    """A heartbeat and a position as MAVLink 2, a signed one, and a MAVLink 1 heartbeat."""
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    heartbeat = mav.heartbeat_encode(2, 3, 0, 0, 4).pack(mav)
    position = mav.global_position_int_encode(1000, 473977420, 85455940, 498000, 10000, 0, 0, 0, 0)
    signed = Signer(b"k" * 32).sign_frame(heartbeat)
    v1 = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    v1.WIRE_PROTOCOL_VERSION = "1.0"
    return [
        heartbeat,
        position.pack(mav),
        signed,
        bytes(v1.heartbeat_encode(2, 3, 0, 0, 4).pack(v1)),
    ]


def test_the_framer_cuts_whole_packets_across_chunks_and_skips_noise() -> None:
    wanted = packets()
    stream = b"\x00junk" + b"".join(wanted)
    framer = MavlinkFramer()
    got: list[bytes] = []
    for k in range(0, len(stream), 7):  # TCP chunks that split every packet
        got += framer.frames(stream[k : k + 7])
    assert got == wanted
    assert MavlinkFramer().frames(wanted[0][:5]) == []


def test_a_tlog_reads_back_with_pymavlink(tmp_path: Path) -> None:
    path = tlog_path(tmp_path)
    assert path.name.startswith("drone_") and path.suffix == ".tlog"
    writer = TlogWriter(path)
    before = time.time()
    writer.record(packets())
    writer.close()
    log = mavutil.mavlink_connection(str(path))
    kinds = []
    while (message := log.recv_match()) is not None:
        kinds.append(message.get_type())
        assert before - 1 <= message._timestamp <= time.time() + 1
    assert kinds == ["HEARTBEAT", "GLOBAL_POSITION_INT", "HEARTBEAT", "HEARTBEAT"]


def test_a_growing_tlog_is_read_record_by_record(tmp_path: Path) -> None:
    """tlog_records: whole records only, a half-written one left for the next read."""
    path = tlog_path(tmp_path)
    writer = TlogWriter(path)
    wanted = packets()
    before = time.time()
    writer.record(wanted)
    writer.close()
    data = path.read_bytes()
    records, used = tlog_records(data)
    assert [packet for _, packet in records] == wanted and used == len(data)
    assert all(before - 1 <= at <= time.time() + 1 for at, _ in records)
    records, used = tlog_records(data[:-3])  # the last record not written whole yet
    assert len(records) == 3 and used == len(data) - 8 - len(wanted[-1])
    # The rest, once written, from where the last read stopped (one call: one stamp).
    assert tlog_records(data[used:]) == ([(records[0][0], wanted[-1])], len(data) - used)


def test_an_unwritable_folder_is_named(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    try:
        TlogWriter(blocker / "x.tlog")
    except OSError as exc:
        assert "telemetry log" in str(exc) and "--tlog-dir" in str(exc)
    else:
        raise AssertionError("a tlog under a file was opened")


def test_the_sitl_witness_reads_the_autopilots_word_and_what_reached_it(tmp_path: Path) -> None:
    """helpers/vehicles.Tlog, the SITL variants' witness, on a log written as the drone
    writes one: ArduCopter's modes and battery from its own frames (system 1), the
    flight commands from the drone's (system 245); reads, rates and a fence item are none."""
    autopilot = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    drone = mavlink.MAVLink(None, srcSystem=245, srcComponent=190)
    quad, apm = mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    armed = mavlink.MAV_MODE_FLAG_SAFETY_ARMED | mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED

    def beat(mode: str, flags: int = armed) -> bytes:
        number = COPTER_MODES[mode]
        return bytes(autopilot.heartbeat_encode(quad, apm, flags, number, 4).pack(autopilot))

    def command(number: int, *params: float) -> bytes:
        padded = [*params, 0, 0, 0, 0, 0, 0, 0][:7]
        return bytes(drone.command_long_encode(1, 1, number, 0, *padded).pack(drone))

    def battery(percent: int) -> bytes:
        status = autopilot.sys_status_encode(0, 0, 0, 0, 12600, 2900, percent, 0, 0, 0, 0, 0, 0)
        return bytes(status.pack(autopilot))

    fence_item = drone.mission_item_int_encode(
        1,
        1,
        0,
        mavlink.MAV_FRAME_GLOBAL,
        mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
        0,
        0,
        6,
        0,
        0,
        0,
        473977420,
        85455940,
        0,
        mavlink.MAV_MISSION_TYPE_FENCE,
    )
    gcs_beat = drone.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    writer = TlogWriter(tmp_path / "drone_1.tlog")
    interval = mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
    writer.record([bytes(fence_item.pack(drone)), beat("GUIDED"), battery(85)])
    writer.record([command(interval, 33, 50000), bytes(gcs_beat.pack(drone))])
    time.sleep(0.01)
    before_return = time.time()
    time.sleep(0.01)
    writer.record([battery(79), command(mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH)])
    writer.record([beat("RTL"), beat("RTL"), command(mavlink.MAV_CMD_DO_SET_MODE, 1, 9)])
    writer.close()
    writer = TlogWriter(tmp_path / "drone_2.tlog")  # the restarted drone's log
    disarmed = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED  # ArduPilot sets it in every one
    writer.record([beat("RTL", disarmed), beat("LAND", disarmed)])
    writer.close()

    tlog = Tlog(tmp_path)
    modes = [(r.mode, r.armed) for r in tlog.modes()]
    assert modes == [
        ("GUIDED", True),
        ("RTL", True),
        ("RTL", True),
        ("RTL", False),
        ("LAND", False),
    ]
    rtl = tlog.first_mode("RTL", after=before_return)
    assert rtl is not None and rtl.at > before_return and tlog.first_mode("BRAKE") is None
    assert [r.mode for r in tlog.entered("RTL")] == ["RTL"]
    sent = tlog.sent()
    assert [(c.what, c.system, c.returns, c.lands) for c in sent] == [
        ("MAV_CMD_NAV_RETURN_TO_LAUNCH", 245, True, False),
        ("MAV_CMD_DO_SET_MODE LAND", 245, False, True),
    ]
    assert tlog.sent(after=sent[-1].at) == []
    assert [pct for _, pct in tlog.battery_remaining()] == [85, 79]
    assert math.isnan(tlog.ground_speed_m_s())
