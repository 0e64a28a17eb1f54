"""A flood of calls for one mission on a station, from a process of its own (so that its
CPU is not the test's event loop): ``Flood`` starts it, lets it go and stops it.

Once told to go, the process keeps up, as fast as it can and all at once:

- ``status``: GetStatus naming the mission on the station's port, as a station of
  the mission's ring (its certificate), twice as many calls at a time as the port
  takes from one caller for one mission (``CALLS_PER_CALLER``);
- ``frames``: LogRing streams naming the mission, each sending garbage frames;
- ``program``: GetPosition on the mission's program port with the program's token
  (what its program, or anything that holds its token, can send), ``PROGRAM_CALLS``
  callers each calling again as soon as its call ends.

It prints ``ready`` once connected, ``flooding`` once each kind of call was answered
``ANNOUNCE_AFTER`` times, and at the end one JSON line: each kind's answers by
status code.
"""

from __future__ import annotations

import asyncio
import json
import sys
from collections import Counter
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path

import grpc

from baton.rpc.admission import CALLS_PER_CALLER
from baton.rpc.channels import aio_channel
from baton.rpc.mission import MISSION_TOKEN_METADATA, mission_metadata
from baton.rpc.tls import Identity, Tls
from baton.v1 import ring_pb2, ring_pb2_grpc

STATUS_CALLS = 2 * CALLS_PER_CALLER
RING_STREAMS = 4
PROGRAM_CALLS = 1000
ANNOUNCE_AFTER = 5
KINDS = ("status", "frames", "program")
GARBAGE = b"\xff\xff not a LogFrame"
GET_POSITION = "/baton.v1.Mobility/GetPosition"
LOG_RING = "/baton.v1.ControllerRing/LogRing"
# How long the process may take to say it is ready, flooding, or done.
SAYS_WITHIN_S = 60.0


@dataclass(frozen=True)
class Target:
    """Whom the flood is for: mission ``mission`` on station ``station_id`` at
    ``address``, called as controller ``as_id`` (a station of the mission's ring) with a
    certificate of ``certs``; and its program's port and token there."""

    address: str
    station_id: int
    mission: str
    certs: Path
    as_id: int
    program_address: str
    program_token: str

    def argv(self) -> list[str]:
        return [
            self.address,
            str(self.station_id),
            self.mission,
            str(self.certs),
            str(self.as_id),
            self.program_address,
            self.program_token,
        ]


class Flood:
    """The flooding process: ``start`` (connected, idle), ``go``, ``stop`` (its answers
    by kind and status code); ``kill`` if the test ends before ``stop``."""

    def __init__(self, target: Target) -> None:
        self.target = target
        self._process: asyncio.subprocess.Process | None = None

    async def _says(self, expected: str) -> None:
        assert self._process is not None and self._process.stdout is not None
        line = await asyncio.wait_for(self._process.stdout.readline(), SAYS_WITHIN_S)
        assert line.decode().strip() == expected, f"the flood said {line!r}, not {expected!r}"

    async def start(self) -> None:
        self._process = await asyncio.create_subprocess_exec(
            sys.executable,
            __file__,
            *self.target.argv(),
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE,
        )
        await self._says("ready")

    async def go(self) -> None:
        """Starts the flood; returns once every kind of call is being answered."""
        assert self._process is not None and self._process.stdin is not None
        self._process.stdin.write(b"go\n")
        await self._process.stdin.drain()
        await self._says("flooding")

    async def stop(self) -> dict[str, dict[str, int]]:
        """Ends the flood: every kind's answers by status code."""
        assert self._process is not None and self._process.stdin is not None
        self._process.stdin.close()
        out, _ = await asyncio.wait_for(self._process.communicate(), SAYS_WITHIN_S)
        assert self._process.returncode == 0, out
        answers: dict[str, dict[str, int]] = json.loads(out.decode().splitlines()[-1])
        return answers

    def kill(self) -> None:
        if self._process is not None and self._process.returncode is None:
            self._process.kill()


class _Tally:
    """Answers by kind and status code; ``flooding`` is set once every kind has some."""

    def __init__(self) -> None:
        self.answers: dict[str, Counter[str]] = {kind: Counter() for kind in KINDS}
        self.flooding = asyncio.Event()

    def count(self, kind: str, code: grpc.StatusCode) -> None:
        self.answers[kind][code.name] += 1
        if all(sum(c.values()) >= ANNOUNCE_AFTER for c in self.answers.values()):
            self.flooding.set()


async def _again(kind: str, tally: _Tally, call: Callable[[], Awaitable[object]]) -> None:
    """``call`` again and again, each answer counted."""
    while True:
        try:
            await call()
            tally.count(kind, grpc.StatusCode.OK)
        except grpc.aio.AioRpcError as exc:
            tally.count(kind, exc.code())


async def _garbage() -> AsyncIterator[bytes]:
    while True:
        yield GARBAGE


async def _flood(target: Target) -> dict[str, Counter[str]]:
    tls = Tls.load(target.certs, Identity.controller(target.as_id))
    named = mission_metadata(target.mission)
    station = aio_channel(target.address, tls, Identity.controller(target.station_id))
    program = aio_channel(target.program_address)
    get_status = ring_pb2_grpc.ControllerRingStub(station).GetStatus
    log_ring: grpc.aio.StreamStreamMultiCallable[bytes, bytes] = station.stream_stream(LOG_RING)
    position: grpc.aio.UnaryUnaryMultiCallable[bytes, bytes] = program.unary_unary(GET_POSITION)
    as_program = ((MISSION_TOKEN_METADATA, target.program_token),)

    async def status() -> None:
        await get_status(ring_pb2.GetControllerStatusRequest(), metadata=named)

    async def frames() -> None:
        async for _ in log_ring(_garbage(), metadata=named):
            pass

    async def call_program() -> None:
        await position(b"", metadata=as_program)

    await station.channel_ready()
    await program.channel_ready()
    print("ready", flush=True)
    loop = asyncio.get_running_loop()
    await loop.run_in_executor(None, sys.stdin.readline)  # "go"
    tally = _Tally()
    callers = [
        *(_again("status", tally, status) for _ in range(STATUS_CALLS)),
        *(_again("frames", tally, frames) for _ in range(RING_STREAMS)),
        *(_again("program", tally, call_program) for _ in range(PROGRAM_CALLS)),
    ]
    tasks = [asyncio.create_task(caller) for caller in callers]
    await tally.flooding.wait()
    print("flooding", flush=True)
    await loop.run_in_executor(None, sys.stdin.read)  # until stdin closes
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    await station.close()
    await program.close()
    return tally.answers


if __name__ == "__main__":
    address, station_id, mission, certs, as_id, program_address, token = sys.argv[1:]
    target = Target(
        address, int(station_id), mission, Path(certs), int(as_id), program_address, token
    )
    print(json.dumps(asyncio.run(_flood(target))), flush=True)
