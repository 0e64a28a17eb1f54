"""``baton bench replay``: how fast ``baton replay`` checks a saved log.

Writes the log of a bench-mission run of ``calls`` requests (half position
reads, half one-second sleeps, ``per_message`` entries to a log message, as
a controller's log file holds them: ``LogHistory``), then times
``replay_log`` on it, end to end: reading the file, feeding the protocol,
loading the mission file and running it through the SDK. The target is a
10,000-call log in under a second (issue 14).
"""

from __future__ import annotations

import statistics
from pathlib import Path
from typing import Any

from baton.bench.runner import machine, say, write_json
from baton.bench.script import BENCH_MISSION, CLOCK_SLEEP, GET_POSITION, bench_mission_args
from baton.controller.history import LogHistory
from baton.digest import request_digest
from baton.replay.replayer import replay_log
from baton.testbed.local import remove_sqlite
from baton.v1 import drone_api_pb2 as api
from baton.v1 import ring_pb2

TARGET_S = 1.0


def bench_script(calls: int) -> str:
    """The bench mission's script of ``calls`` requests."""
    return f"p*{calls // 2},s1*{calls - calls // 2}"


def write_bench_log(path: Path, calls: int, per_message: int = 100) -> None:
    """The log file a ring would keep of ``bench_script(calls)``."""
    position = api.GetPositionReply(
        position=api.Position(latitude_deg=47.1, longitude_deg=8.5, absolute_altitude_m=500.0)
    ).SerializeToString()
    sleep = api.SleepRequest(seconds=1.0).SerializeToString()
    slept = api.SleepReply().SerializeToString()
    entries = []
    for reqnr in range(1, calls + 1):
        method, request, reply = (
            (GET_POSITION, b"", position) if reqnr <= calls // 2 else (CLOCK_SLEEP, sleep, slept)
        )
        entries.append(
            ring_pb2.LogEntry(
                reqnr=reqnr,
                method=method,
                reply=reply,
                request=request,
                request_digest=request_digest(method, request),
            )
        )
    remove_sqlite(path)
    history = LogHistory(path)
    try:
        for k in range(0, calls, per_message):
            chunk = entries[k : k + per_message]
            history.add(
                ring_pb2.LogMessage(
                    lognr=k // per_message + 1,
                    origin=0,
                    epoch=1,
                    entries=chunk,
                    after_reqnr=k,
                    after_epoch=1 if k else 0,
                )
            )
    finally:
        history.close()


def run_replay_bench(out: Path, calls: int, passes: int) -> dict[str, Any]:
    """Writes the log under ``out``, replays it ``passes`` times, writes and returns the result."""
    out.mkdir(parents=True, exist_ok=True)
    log = out / f"bench-log-{calls}.sqlite"
    say(f"replay: writing a {calls}-call log to {log}")
    write_bench_log(log, calls)
    args = list(bench_mission_args(bench_script(calls)))
    seconds = []
    for _ in range(passes):
        outcome = replay_log(log, str(BENCH_MISSION), args)
        if not outcome.clean or outcome.replayed != calls:
            raise RuntimeError(f"the bench log did not replay clean: {outcome}")
        seconds.append(outcome.seconds)
    median = statistics.median(seconds)
    result = {
        "calls": calls,
        "passes": passes,
        "seconds": seconds,
        "median_s": median,
        "calls_per_s": calls / median,
        "target_s": TARGET_S * calls / 10_000,
        "log": str(log),
        "command": (f"baton replay {log} --mission {BENCH_MISSION} --mission-arg {' '.join(args)}"),
        "machine": machine(),
    }
    write_json(out / "replay.json", result)
    return result
