"""Running testbed missions for the benchmarks, and reading the results back.

One place for what every benchmark does around a run: start the local
testbed, print progress lines while the mission runs, turn the drone's audit
into the calls the model works on, and describe the machine it ran on.
"""

from __future__ import annotations

import json
import platform
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from baton.bench.model import Call
from baton.controller.core import CLOCK_SLEEP
from baton.testbed.local import LocalTestbed, Snapshot, TestbedPlan
from baton.v1 import ring_pb2


def say(text: str) -> None:
    """One progress line on stdout."""
    print(f"[{time.strftime('%H:%M:%S')}] {text}", flush=True)


async def run_plan(plan: TestbedPlan, workdir: Path, timeout: float, label: str) -> Snapshot:
    """Runs one mission on a fresh local testbed; prints progress as requests arrive."""
    workdir.mkdir(parents=True, exist_ok=True)
    seen = {"reqnr": -1, "handovers": -1}

    def progress(snapshot: Snapshot) -> None:
        drone = snapshot.drone
        if (drone.last_reqnr, len(drone.handovers)) != (seen["reqnr"], seen["handovers"]):
            seen["reqnr"], seen["handovers"] = drone.last_reqnr, len(drone.handovers)
            done = sum(1 for h in drone.handovers if h.delay_s > 0)
            say(
                f"{label}: reqnr {drone.last_reqnr}, master {drone.master}, "
                f"handovers {done}/{len(plan.handovers)}"
            )

    say(f"{label}: starting {len(plan.config.controllers)} controllers in {workdir}")
    async with LocalTestbed(plan, workdir) as testbed:
        snapshot = await testbed.run_mission(timeout, progress, period=1.0)
    failed = {
        cid: c.mission_error
        for cid, c in snapshot.controllers.items()
        if c.mission != ring_pb2.MISSION_STATE_DONE
    }
    if failed:
        raise RuntimeError(f"{label}: mission failed on controllers {failed}")
    return snapshot


# Request numbers the drone never sees are the controller's own Clock calls
# (Sleep, logged with its request and an empty reply): a Sleep of one second.
CLOCK_CALL = (CLOCK_SLEEP, 0, 9)


def audit_calls(
    snapshot: Snapshot,
    request_bytes: Mapping[int, int] | None = None,
    methods: Mapping[int, str] | None = None,
) -> list[Call]:
    """Every request of the run as model calls, in reqnr order.

    The drone's audit gives method and reply size of what it executed; the
    gaps are calls the controller answered itself (``Clock``), taken from
    ``methods`` and ``request_bytes`` where known, else as a Clock.Sleep.
    """
    sizes = request_bytes or {}
    audit = {a.reqnr: a for a in snapshot.drone.audit}
    calls = []
    for reqnr in range(1, max(audit, default=0) + 1):
        entry = audit.get(reqnr)
        if entry is not None:
            calls.append(Call(reqnr, entry.method, entry.reply_bytes, sizes.get(reqnr, 0)))
        else:
            method, reply, request = CLOCK_CALL
            method = (methods or {}).get(reqnr, method)
            calls.append(Call(reqnr, method, reply, sizes.get(reqnr, request)))
    return calls


def t_conn_samples(snapshot: Snapshot) -> list[float]:
    """Every drone connection set-up time the controllers measured, seconds."""
    return [t for c in snapshot.controllers.values() for t in c.t_conn_s]


def machine() -> dict[str, Any]:
    """What the numbers were measured on."""
    cpu = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import os

    return {
        "nproc": os.cpu_count(),
        "cpu": cpu,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
    }


def write_json(path: Path, data: Any) -> None:
    """Writes ``data`` as indented JSON."""
    path.write_text(json.dumps(data, indent=2) + "\n")


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A GitHub markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"
