"""The model: the paper's performance model (Section 4) and the master's log, predicted.

The one place both live: the testbed's report (its handovers' model worst
case) and the benchmarks read them here.

``t_log`` and ``t_max`` are the paper's formulas: T_log(s) = l + s/b and
T_max = T_log(0) + h * T_log(f + e) + T_conn, sizes in bytes, b in bit/s
(``None``: unlimited, as ``LinkSpec.bandwidth`` says it; the transfer then
takes no time).

``PredictedRing`` predicts the master's log by running the protocol itself
(``controller/protocol.py``): a master and a replica, each a
``ControllerProtocol``, are given the drone's replies (``on_reply``, where
the flush rule of Algorithm 1, lines 15-21, lives) and the drone's handover
notices, and pass each other the log messages that come out; so the
benchmarks can say, before a run, where the master's log holds how much,
and after a run, what it held at every request, with no copy of the rule.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

from baton.controller.protocol import ControllerProtocol, Effect, Log, SendLog, State, entry_size
from baton.digest import request_digest
from baton.v1 import ring_pb2

MB = 2**20
PAPER_LATENCY_S = 0.020
PAPER_BANDWIDTH_BIT_S = 25e6


def t_log(size_bytes: float, latency_s: float, bandwidth_bit_s: float | None) -> float:
    """T_log(s) = l + s/b: time to send a log message of ``size_bytes`` to the next
    controller (``bandwidth_bit_s`` None: unlimited, the latency alone)."""
    transfer = 0.0 if bandwidth_bit_s is None else 8 * size_bytes / bandwidth_bit_s
    return latency_s + transfer


def preparation_limit(
    start_bytes: int,
    later: Iterable[tuple[float, int]],
    ring_latency_s: float,
    ring_bandwidth_bit_s: float | None,
    drone_latency_s: float,
    drone_bandwidth_bit_s: float | None,
) -> float:
    """The physical limit of a prepared handover's preparation, timed as the drone times
    it (its decision to prepare to its decision to move the master).

    The drone's PrepareHandover crosses the drone link; the master's log at that
    moment (``start_bytes``) and then every reply the target lacks too (``later``:
    a picture taken meanwhile, as (seconds after the drone's decision that the drone
    got its request, bytes); its bytes exist at the master only once the reply
    crossed the drone link) cross one ring link one after the other; the target's
    acknowledgement comes back over the ring link, and the master's word over the
    drone link. Nothing else: no processing, no framing, no contention.
    """

    def transfer(size: float, bandwidth: float | None) -> float:
        return t_log(size, 0.0, bandwidth)

    free = drone_latency_s + transfer(start_bytes, ring_bandwidth_bit_s)
    for requested_s, size in sorted(later):
        at_master = requested_s + t_log(size, drone_latency_s, drone_bandwidth_bit_s)
        free = max(free, at_master) + transfer(size, ring_bandwidth_bit_s)
    return free + 2 * ring_latency_s + drone_latency_s


def t_max(
    flush_limit: float,
    largest_entry: float,
    hops: int,
    t_conn_s: float,
    latency_s: float = PAPER_LATENCY_S,
    bandwidth_bit_s: float | None = PAPER_BANDWIDTH_BIT_S,
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
    """A synthetic log entry of the same serialized size as the real one for ``call``
    (with the real digest of its synthetic request, which a replica replays)."""
    request = b"\1" * call.request_bytes
    return ring_pb2.LogEntry(
        reqnr=call.reqnr,
        method=call.method,
        reply=b"\1" * call.reply_bytes,
        request_digest=request_digest(call.method, request),
        request=request,
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


class PredictedRing:
    """The master's log, predicted by running Algorithm 1 on two controllers.

    The master is given each call's reply (``reply``); the log messages it
    flushes go to the other controller, which handles and replays them as
    a replica does; at a handover (``hand_over``) the master hands its
    unflushed log to the other one, which replays it and becomes the new
    master with an empty log (Algorithm 1, lines 24-29, 52). The log's
    size does not depend on how many controllers the ring has, so two do.
    Calls are numbered 1, 2, 3, ... like the drone numbers requests.
    """

    def __init__(self, flush_limit: int) -> None:
        self.flush_limit = flush_limit
        self._nodes = {cid: ControllerProtocol(cid, [0, 1], flush_limit) for cid in (0, 1)}
        for node in self._nodes.values():
            node.start()
            node.on_sync(0)  # the mission's start: the predecessor holds nothing yet
        self._master = 0
        self._epoch = 1
        self._nodes[0].on_granted(self._epoch)

    @property
    def master(self) -> ControllerProtocol:
        """The current master's protocol."""
        return self._nodes[self._master]

    @property
    def size(self) -> int:
        """Bytes in the master's log now."""
        return self.master.log.size

    def reply(self, call: Call) -> LogPoint:
        """The master logs ``call``'s reply; the log after it, and what it flushed."""
        if call.reqnr != self.master.reqnr + 1:
            raise ValueError(
                f"call {call.reqnr} follows request {self.master.reqnr}: the model's calls "
                "are numbered 1, 2, 3, ... in order, as the drone numbers requests"
            )
        effects = self.master.on_reply(log_entry(call))
        sent = [e for e in effects if isinstance(e, SendLog)]
        flushed = sum(entry_size(entry) for entry in sent[0].message.entries) if sent else 0
        self._deliver(effects)
        return LogPoint(call.reqnr, self.size, flushed)

    def hand_over(self) -> None:
        """The drone hands over to the other controller after the last call."""
        new_master = 1 - self._master
        self._epoch += 1
        self._deliver(self.master.on_handover_notice(new_master, self._epoch))
        self._master = new_master
        self._deliver(self.master.on_granted(self._epoch))
        if self.master.state is not State.ACTIVE:
            raise AssertionError(f"the predicted new master is {self.master.state.name}")

    def _deliver(self, effects: list[Effect]) -> None:
        """Hands every log message sent to its controller, which replays what it logs."""
        pending = list(effects)
        while pending:
            effect = pending.pop(0)
            if not isinstance(effect, SendLog):
                continue  # the drone connection: nothing to predict
            node = self._nodes[effect.dest]
            pending.extend(node.on_log(effect.message))
            while node.state is State.REPLAY:
                entry = node.log.entries[0]
                pending.extend(node.replay(entry.method, entry.request)[1])


def master_log_sizes(
    calls: Iterable[Call], flush_limit: int, handovers: Sequence[int] = ()
) -> list[LogPoint]:
    """The master's log after every call, by the protocol's flush rule.

    ``handovers`` are the reqnrs after which the drone hands over: the old
    master sends its log with the handover message, and the new master starts
    from an empty log once it has replayed it (Algorithm 1, lines 24-29, 52).
    """
    after = set(handovers)
    ring = PredictedRing(flush_limit)
    points: list[LogPoint] = []
    for call in calls:
        points.append(ring.reply(call))
        if call.reqnr in after:
            ring.hand_over()
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
