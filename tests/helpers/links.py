"""The link emulator as a process; a radio station and a vehicle placed in its range."""

from __future__ import annotations

import asyncio
import contextlib
import json
import signal
import sys
from collections.abc import AsyncIterator
from pathlib import Path

from baton.link.radio import RadioRange, write_position
from baton.sdk import Position, offset

STATION = Position(47.397742, 8.545594)


RADIO = RadioRange(STATION.latitude_deg, STATION.longitude_deg, 500.0)


def place(path: Path, east_m: float) -> None:
    """The vehicle's position file says it is ``east_m`` east of the station."""
    where = offset(STATION, 0.0, east_m)
    write_position(path, where.latitude_deg, where.longitude_deg, 10.0)


class LinkProcess:
    """A running ``baton link`` subprocess and its listening address."""

    def __init__(self, process: asyncio.subprocess.Process, address: str) -> None:
        self.process = process
        self.address = address

    async def terminate(self) -> tuple[int, list[dict]]:
        """SIGTERM; returns the exit code and the JSON log lines."""
        self.process.send_signal(signal.SIGTERM)
        _, stderr = await asyncio.wait_for(self.process.communicate(), 10)
        assert self.process.returncode is not None
        lines = []
        for line in stderr.splitlines():
            try:
                lines.append(json.loads(line))
            except ValueError:  # once under load on 2 cores: say what it was
                raise AssertionError(f"baton link wrote a line not JSON: {line!r}") from None
        return self.process.returncode, lines


@contextlib.asynccontextmanager
async def baton_link(target: str, *options: str) -> AsyncIterator[LinkProcess]:
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "baton.cli",
        "link",
        "--target",
        target,
        *options,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    try:
        assert process.stdout is not None
        line = await asyncio.wait_for(process.stdout.readline(), 20)
        event = json.loads(line)
        assert event["event"] == "listening"
        yield LinkProcess(process, event["address"])
    finally:
        if process.returncode is None:
            process.kill()
            await process.wait()
