"""The paper's performance model (Section 4) and the master's log, computed offline.

``t_log`` and ``t_max`` are the paper's formulas: T_log(s) = l + s/b and
T_max = T_log(0) + h * T_log(f + e) + T_conn, sizes in bytes, b in bit/s.

``master_log_sizes`` replays Algorithm 1's flush rule (lines 15-21) over a
request sequence with the protocol's own ``Log`` and ``entry_size``, so the
benchmarks can say, before a run, where the master's log holds how much,
and after a run, what it held at every request.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

from baton.controller.protocol import Log
from baton.v1 import ring_pb2

MB = 2**20
PAPER_LATENCY_S = 0.020
PAPER_BANDWIDTH_BIT_S = 25e6
DIGEST_BYTES = 32  # SHA-256 request digest in every log entry


def t_log(size_bytes: float, latency_s: float, bandwidth_bit_s: float) -> float:
    """T_log(s) = l + s/b: time to send a log message of ``size_bytes`` to the next controller."""
    return latency_s + 8 * size_bytes / bandwidth_bit_s


def t_max(
    flush_limit: float,
    largest_entry: float,
    hops: int,
    t_conn_s: float,
    latency_s: float = PAPER_LATENCY_S,
    bandwidth_bit_s: float = PAPER_BANDWIDTH_BIT_S,
) -> float:
    """The paper's worst-case handover delay T_log(0) + h * T_log(f + e) + T_conn."""
    return (
        t_log(0, latency_s, bandwidth_bit_s)
        + hops * t_log(flush_limit + largest_entry, latency_s, bandwidth_bit_s)
        + t_conn_s
    )


@dataclass(frozen=True)
class Call:
    """One request as the master logs it: what the log entry's size depends on."""

    reqnr: int
    method: str
    reply_bytes: int
    request_bytes: int = 0


def log_entry(call: Call) -> ring_pb2.LogEntry:
    """A synthetic log entry of the same serialized size as the real one for ``call``."""
    return ring_pb2.LogEntry(
        reqnr=call.reqnr,
        method=call.method,
        reply=b"\1" * call.reply_bytes,
        request_digest=b"\1" * DIGEST_BYTES,
        request=b"\1" * call.request_bytes,
    )


def entry_size_of(call: Call) -> int:
    """Bytes that ``call``'s entry adds to the master's log."""
    log = Log()
    log.append(log_entry(call))
    return log.size


@dataclass(frozen=True)
class LogPoint:
    """The master's log right after request ``reqnr``; ``flushed`` bytes went on the ring."""

    reqnr: int
    size: int  # bytes in the log after this request (0 right after a flush)
    flushed: int  # size of the log message flushed at this request; 0 if none


def master_log_sizes(
    calls: Iterable[Call], flush_limit: int, handovers: Sequence[int] = ()
) -> list[LogPoint]:
    """The master's log after every call, by the flush rule ``size(log) >= flush``.

    ``handovers`` are the reqnrs after which the drone hands over: the old
    master sends its log with the handover message, and the new master starts
    from an empty log once it has replayed it (Algorithm 1, lines 24-29, 52).
    """
    after = set(handovers)
    log = Log()
    points: list[LogPoint] = []
    for call in calls:
        log.append(log_entry(call))
        flushed = 0
        if log.size >= flush_limit:
            flushed = log.size
            log.take()
        points.append(LogPoint(call.reqnr, log.size, flushed))
        if call.reqnr in after:
            log.take()
    return points


def pick_in_stretch(
    points: Sequence[LogPoint],
    target: float,
    tolerance: float,
    eligible: Callable[[LogPoint], bool] = lambda p: True,
    end_margin: int = 2,
) -> int | None:
    """A reqnr late in the first stretch of requests with a log within ``tolerance`` of ``target``.

    A stretch is a run of consecutive points all near the target. Late in it,
    the flush that began the stretch has had the most time to travel; a
    couple of requests before its end (``end_margin``), a run whose timing
    differs by a request or two still lands in the same stretch. Returns None
    if no eligible point is near the target.
    """
    stretch: list[LogPoint] = []
    stretches: list[list[LogPoint]] = []
    for point in points:
        if abs(point.size - target) <= tolerance:
            stretch.append(point)
        elif stretch:
            stretches.append(stretch)
            stretch = []
    if stretch:
        stretches.append(stretch)
    for run in stretches:
        picks = [p for p in run if eligible(p)]
        if picks:
            return picks[max(0, len(picks) - 1 - end_margin)].reqnr
    return None
