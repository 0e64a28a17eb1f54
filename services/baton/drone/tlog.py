"""The drone's telemetry log: its MAVLink traffic with the autopilot, as a ``.tlog``.

A ``.tlog`` is what QGroundControl and MAVProxy record and what pymavlink's
tools read (``mavlogdump.py``, ``mavtogpx.py``, MAVExplorer): each MAVLink
packet as it crossed the link, after an 8-byte big-endian timestamp in
microseconds since the Unix epoch. The drone service records one per run
(``baton drone --tlog-dir DIR``), in both directions, from the relay that
stands between MAVSDK and the autopilot (``drone/mavlink_relay.py``): the
bytes are teed there, with no second connection to the autopilot.

``MavlinkFramer`` cuts a byte stream (TCP chunks, UDP datagrams) into whole
packets by their headers alone, without decoding them: a packet of any
dialect is recorded as it was.
"""

from __future__ import annotations

import os
import struct
import time
from pathlib import Path
from typing import BinaryIO

V1_MAGIC = 0xFE
V2_MAGIC = 0xFD
_V1_OVERHEAD = 6 + 2  # magic, len, seq, sys, comp, msgid; CRC
_V2_OVERHEAD = 10 + 2  # magic, len, incompat, compat, seq, sys, comp, msgid (3); CRC
_V2_SIGNATURE = 13
_V2_SIGNED = 0x01
# A telemetry log is flushed to the file at least this often: a kill -9 loses less.
FLUSH_S = 0.5


def frame_size(head: bytes | bytearray) -> int | None:
    """The whole size of the MAVLink packet ``head`` starts with (a magic byte first, its
    header read from the first 3 bytes); None while fewer than 3 are there."""
    if len(head) < 3:
        return None
    if head[0] == V1_MAGIC:
        return _V1_OVERHEAD + head[1]
    if head[0] != V2_MAGIC:
        raise ValueError(f"no MAVLink packet starts here (byte {head[0]:#04x})")
    return _V2_OVERHEAD + head[1] + (_V2_SIGNATURE if head[2] & _V2_SIGNED else 0)


def tlog_records(data: bytes) -> tuple[list[tuple[float, bytes]], int]:
    """The whole records at the start of ``data`` (a ``.tlog``'s bytes from a record's
    start), each (Unix seconds, packet), and the bytes they take: a record still being
    written is left for a later read, so a log can be read as it grows."""
    records: list[tuple[float, bytes]] = []
    at = 0
    while (size := frame_size(data[at + 8 : at + 11])) is not None and at + 8 + size <= len(data):
        (micros,) = struct.unpack_from(">Q", data, at)
        records.append((micros / 1e6, data[at + 8 : at + 8 + size]))
        at += 8 + size
    return records, at


class MavlinkFramer:
    """Whole MAVLink 1 and 2 packets out of a byte stream, across chunk boundaries."""

    def __init__(self) -> None:
        self._buffer = bytearray()

    def frames(self, data: bytes) -> list[bytes]:
        """The packets completed by ``data``; bytes before a magic byte are skipped."""
        buffer = self._buffer
        buffer += data
        frames: list[bytes] = []
        while buffer:
            starts = [i for i in (buffer.find(V2_MAGIC), buffer.find(V1_MAGIC)) if i >= 0]
            if not starts:
                buffer.clear()
                break
            del buffer[: min(starts)]
            size = frame_size(buffer)
            if size is None or len(buffer) < size:
                break
            frames.append(bytes(buffer[:size]))
            del buffer[:size]
        return frames


def tlog_path(folder: Path) -> Path:
    """This run's telemetry log in ``folder``: named for the UTC time it started (as QGC
    names its logs) and the process, so a restarted drone service starts another."""
    stamp = time.strftime("%Y-%m-%d_%H-%M-%S", time.gmtime())
    return folder / f"drone_{stamp}_{os.getpid()}.tlog"


class TlogWriter:
    """Appends packets to a ``.tlog`` file, each after its receive time."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._file: BinaryIO = path.open("ab")
        except OSError as exc:
            raise OSError(
                f"telemetry log {path} (--tlog-dir): {exc.strerror}; give a writable folder"
            ) from exc
        self.packets = 0
        self._flushed_at = time.monotonic()

    def record(self, frames: list[bytes]) -> None:
        """Writes ``frames`` (whole packets), stamped now."""
        if not frames or self._file.closed:
            return
        stamp = struct.pack(">Q", int(time.time() * 1e6))
        self._file.write(b"".join(stamp + frame for frame in frames))
        self.packets += len(frames)
        now = time.monotonic()
        if now - self._flushed_at >= FLUSH_S:
            self._file.flush()
            self._flushed_at = now

    def close(self) -> None:
        """Flushes and closes the file."""
        if not self._file.closed:
            self._file.close()
