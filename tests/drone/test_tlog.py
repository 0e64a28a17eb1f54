"""The drone's telemetry log (drone/tlog.py): packets cut from a stream, read back by pymavlink."""

from __future__ import annotations

import time
from pathlib import Path

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from baton.drone.tlog import MavlinkFramer, TlogWriter, tlog_path
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


def test_an_unwritable_folder_is_named(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    try:
        TlogWriter(blocker / "x.tlog")
    except OSError as exc:
        assert "telemetry log" in str(exc) and "--tlog-dir" in str(exc)
    else:
        raise AssertionError("a tlog under a file was opened")
