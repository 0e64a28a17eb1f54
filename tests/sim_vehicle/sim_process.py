"""Running ``baton sim-vehicle`` as a real process, and waiting on conditions."""

from __future__ import annotations

import asyncio
import json
import signal
import sys
from dataclasses import dataclass

from waiting import STEP_TIMEOUT_S, eventually

__all__ = ["STEP_TIMEOUT_S", "SimProcess", "eventually", "start_sim"]


@dataclass
class SimProcess:
    """A running ``baton sim-vehicle`` and the URL it reported."""

    process: asyncio.subprocess.Process
    url: str
    port: int

    async def terminate(self, timeout_s: float = 5.0) -> int:
        """Sends SIGTERM and returns the exit code."""
        if self.process.returncode is None:
            self.process.send_signal(signal.SIGTERM)
        return await asyncio.wait_for(self.process.wait(), timeout_s)


async def start_sim(*args: str) -> SimProcess:
    """Starts a vehicle on a free port and reads its ``listening`` line."""
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "baton.cli",
        "--log-level",
        "warning",
        "sim-vehicle",
        *args,
        stdout=asyncio.subprocess.PIPE,
    )
    assert process.stdout is not None
    line = await asyncio.wait_for(process.stdout.readline(), STEP_TIMEOUT_S)
    event = json.loads(line)
    assert event["event"] == "listening", event
    return SimProcess(process, event["url"], event["port"])
