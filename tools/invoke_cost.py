"""What the gate costs a drone call (docs/benchmarks.md, "The drone's own Invoke"): the
round trip of a direct Invoke (GetPosition) on a drone service in this process, over
a real insecure channel and the tests' fake vehicle, served through every port's gate
(``rpc/gate.py``: a unary method served as request-streaming, so that the caller is
admitted before its request is read) and with unary methods handed to gRPC as they are.
Blocks alternate A B B A, each on a fresh drone; the medians of each block are printed.

    .venv/bin/python tools/invoke_cost.py [BLOCKS] [CALLS]
"""

from __future__ import annotations

import asyncio
import statistics
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT / "tests" / "drone"), str(ROOT / "tests")]

from drone_harness import start_drone  # noqa: E402
from helpers.drone_calls import POSITION, invoke  # noqa: E402

from baton.rpc import gate  # noqa: E402

GATED = gate.Gate._unary_request
WARM_UP = 100


def _as_it_is(self: gate.Gate, method: str, handler: Any) -> Any:
    return handler


async def block(gated: bool, calls: int) -> float:
    """The median round trip (ms) of ``calls`` Invokes on a fresh drone."""
    gate.Gate._unary_request = GATED if gated else _as_it_is  # type: ignore[method-assign]
    drone, server = await start_drone()
    try:
        for reqnr in range(1, WARM_UP + 1):
            await drone.stub.Invoke(invoke(0, reqnr, POSITION))
        samples = []
        for reqnr in range(WARM_UP + 1, WARM_UP + 1 + calls):
            start = time.perf_counter()
            await drone.stub.Invoke(invoke(0, reqnr, POSITION))
            samples.append(time.perf_counter() - start)
    finally:
        await server.stop(0.0)
        gate.Gate._unary_request = GATED  # type: ignore[method-assign]
    return statistics.median(samples) * 1e3


async def main(blocks: int, calls: int) -> None:
    medians: dict[bool, list[float]] = {True: [], False: []}
    for i in range(blocks):
        for gated in (True, False) if i % 2 == 0 else (False, True):
            medians[gated].append(await block(gated, calls))
    for gated, values in medians.items():
        name = "through the gate" if gated else "unary as it is"
        each = ", ".join(f"{v:.3f}" for v in values)
        print(f"{name:17}: p50 {statistics.median(values):.3f} ms (blocks: {each})")


if __name__ == "__main__":
    args = [int(a) for a in sys.argv[1:3]]
    asyncio.run(main(*(args + [6, 1500][len(args) :])))
