"""Running ``baton sim-vehicle`` as a real process, and waiting on conditions."""

from __future__ import annotations

import asyncio
import json
import signal
import sys
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

# Wall-clock budget for any one step of a test, generous for a loaded 2-core CI box.
STEP_TIMEOUT_S = 20.0


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


async def eventually(
    check: Callable[[], Awaitable[Any]], what: str, timeout_s: float = STEP_TIMEOUT_S
) -> Any:
    """Polls ``check`` until it returns something truthy; fails after the deadline."""
    deadline = time.monotonic() + timeout_s
    last: Any = None
    while time.monotonic() < deadline:
        last = await check()
        if last:
            return last
        await asyncio.sleep(0.02)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what} (last: {last!r})")
