"""Each controller's link as the drone sees it: its streams, and its round trip measured.

gRPC's keepalive pings are not visible to the application, so the drone
measures the round trip itself (docs/design.md, "Link health"): every
``PING_PERIOD_S`` it sends a ``LinkPing`` on each controller's newest standby
stream, and the controller answers with the small unary ``AnswerPing`` on the
same channel (so through the same link emulator, and under mutual TLS checked
like Invoke). The round trip is the time from queueing the ping to the
answer's arrival, on the drone's monotonic clock: no clock of the
controller's is trusted. About 120 bytes a second each way per controller
(measured through the link emulator, without TLS).

A ping lost with a broken stream is never answered: a new standby stream
starts its controller's measurement afresh (``attached``). A link judged by
``policy.link_problem`` (the one judgement, shared with the handover policy)
going unhealthy or healthy again is logged (``watch``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from baton.drone.policy import LinkBounds, LinkState, link_problem
from baton.logs import BoundLogger
from baton.v1 import drone_pb2

# How often each controller is pinged (wall seconds).
PING_PERIOD_S = 1.0
# Pings a controller may leave unanswered before the oldest is forgotten (an
# answer to it is then not measured).
PINGS_KEPT = 8


@dataclass
class _Probe:
    """One controller's measurement on its current standby stream."""

    pending: dict[int, float] = field(default_factory=dict)  # seq -> sent (monotonic)
    first_ping_at: float | None = None
    rtt_s: float | None = None
    previous_rtt_s: float | None = None  # the answer before the last one
    answered_at: float | None = None  # monotonic
    measured_sent_at: float = float("-inf")  # when the ping measured was sent


class LinkProbes:
    """The round trip of every controller's link, and its health over time."""

    def __init__(self, controllers: tuple[int, ...], bounds: LinkBounds, log: BoundLogger) -> None:
        self.controllers = controllers
        self.bounds = bounds
        self._probes: dict[int, _Probe] = {cid: _Probe() for cid in controllers}
        self._seq = 0
        self.pings = dict.fromkeys(controllers, 0)
        self.answers = dict.fromkeys(controllers, 0)
        # The last health logged, by controller: its problem ("" healthy).
        self._logged: dict[int, str] = {}
        self._log = log

    def attached(self, controller_id: int) -> None:
        """A new standby stream of ``controller_id``: its pings on the old one are lost."""
        if controller_id in self._probes:
            self._probes[controller_id] = _Probe()

    def ping(self, controller_id: int, now: float) -> drone_pb2.StandbyEvent:
        """The next ping for ``controller_id``, noted as sent at ``now`` (monotonic)."""
        probe = self._probes[controller_id]
        self._seq += 1
        probe.pending[self._seq] = now
        if probe.first_ping_at is None:
            probe.first_ping_at = now
        while len(probe.pending) > PINGS_KEPT:
            del probe.pending[min(probe.pending)]
        self.pings[controller_id] += 1
        return drone_pb2.StandbyEvent(ping=drone_pb2.LinkPing(seq=self._seq))

    def answered(self, controller_id: int, seq: int, now: float) -> bool:
        """``controller_id`` answered ping ``seq`` at ``now``: whether it was measured
        (False for a ping forgotten, of an older stream, or never sent to it)."""
        probe = self._probes.get(controller_id)
        sent = probe.pending.pop(seq, None) if probe is not None else None
        if probe is None or sent is None:
            return False
        # Answers of concurrent calls may arrive out of order: the newest ping's counts.
        if sent >= probe.measured_sent_at:
            probe.previous_rtt_s = probe.rtt_s
            probe.rtt_s, probe.answered_at, probe.measured_sent_at = now - sent, now, sent
        self.answers[controller_id] += 1
        return True

    def measured(self, controller_id: int, now: float) -> tuple[float | None, float | None]:
        """``controller_id``'s round trip and its age (``LinkState``'s), wall seconds: the
        smaller of its last two answers, so one answer late on a loaded machine does not
        make a link slow (CI: a master moved on one such answer); two in a row do."""
        probe = self._probes[controller_id]
        if probe.answered_at is not None:
            last = probe.rtt_s
            if last is not None and probe.previous_rtt_s is not None:
                last = min(last, probe.previous_rtt_s)
            return last, now - probe.answered_at
        if probe.first_ping_at is not None:
            return None, now - probe.first_ping_at
        return None, None

    def state(self, controller_id: int, up: bool, down_for_s: float, now: float) -> LinkState:
        """The link as the policy takes it: ``up`` and ``down_for_s`` from the streams."""
        rtt_s, age_s = self.measured(controller_id, now)
        return LinkState(up=up, down_for_s=down_for_s, rtt_s=rtt_s, rtt_age_s=age_s)

    def problem(self, link: LinkState) -> str:
        """Why ``link`` is not healthy by these bounds; empty if it is."""
        return link_problem(link, self.bounds)

    def status(
        self, controller_id: int, standby: bool, connect: bool, down_for_s: float, now: float
    ) -> drone_pb2.ControllerLink:
        """GetStatus's entry for ``controller_id``."""
        link = self.state(controller_id, standby or connect, down_for_s, now)
        problem = self.problem(link)
        return drone_pb2.ControllerLink(
            controller_id=controller_id,
            standby=standby,
            connect=connect,
            rtt_s=-1.0 if link.rtt_s is None else link.rtt_s,
            rtt_age_s=-1.0 if link.rtt_age_s is None else link.rtt_age_s,
            healthy=not problem,
            problem=problem,
            max_rtt_s=self.bounds.max_rtt_s,
            rtt_stale_s=self.bounds.rtt_stale_s,
            pings=self.pings[controller_id],
            answers=self.answers[controller_id],
        )

    def watch(self, links: dict[int, LinkState]) -> None:
        """Logs each link that went unhealthy or healthy again since the last look."""
        for cid, link in links.items():
            problem = self.problem(link)
            before = self._logged.get(cid)
            if before is None or bool(before) == bool(problem):
                self._logged.setdefault(cid, problem)  # the first look says nothing
                continue
            self._logged[cid] = problem
            fields = {
                "controller": cid,
                "rtt_ms": None if link.rtt_s is None else round(link.rtt_s * 1000, 1),
                "rtt_age_s": None if link.rtt_age_s is None else round(link.rtt_age_s, 2),
            }
            if problem:
                self._log.warning("controller link unhealthy", problem=problem, **fields)
            else:
                self._log.info("controller link healthy", **fields)
