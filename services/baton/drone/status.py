"""The drone's GetStatus: its state, counters, links, waits and (if asked) the audit."""

from __future__ import annotations

import asyncio
import time
from typing import TYPE_CHECKING

from baton.drone.mobility_api import READ_TIMEOUT_S, latest_position
from baton.drone.operator_service import failsafe_proto, fill_status
from baton.rpc.errors import StatusError
from baton.stalls import StallWatch, Wait, drone_conditions, drone_judge
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2

if TYPE_CHECKING:
    from baton.drone.service import DroneService


class StallWatcher:
    """What one ``DroneService`` waits for (``stalls.drone_conditions``), kept for GetStatus."""

    def __init__(self, service: DroneService) -> None:
        self.service = service
        self._stalls = StallWatch()
        self.waits: list[Wait] = []
        self._reached = False  # a controller has reached this process (stalls.py)

    async def run(self) -> None:
        """Every half second: waits into GetStatus, and stalls into the log when they begin."""
        service = self.service
        while True:
            reachable, connected = service.standby.reachable, service.streams.master_connected
            self._reached = self._reached or bool(reachable) or connected
            # Without a policy there is no map: every link should be up. With one,
            # a position not known yet puts no station in range.
            policy = service.policy
            in_range = None if policy is None else (policy.in_range() or set())
            holding = drone_conditions(
                service.seq.master, connected, service.seq.ring, reachable, in_range, self._reached
            )
            holding.update(service.operator.waiting())
            link_up_s = policy.params.link_up_s / policy.speedup if policy is not None else 0.0
            now = time.monotonic()
            self.waits = self._stalls.update(now, holding, drone_judge(link_up_s))
            if self._stalls.due_for_log(now, self.waits):
                service.log.warning("stalled", waiting=service.waiting)
            await asyncio.sleep(0.5)


# Audit entries in one GetStatus page: by default, and at most.
AUDIT_PAGE, AUDIT_PAGE_MAX = 1_000, 10_000


async def drone_status(
    service: DroneService,
    include_audit: bool = False,
    audit_after_reqnr: int = 0,
    audit_limit: int = 0,
) -> drone_pb2.DroneStatus:
    """GetStatus without gRPC; the audit one page at a time (in bounded memory)."""
    seq = service.seq
    status = drone_pb2.DroneStatus(
        master=seq.master,
        epoch=seq.epoch,
        last_reqnr=seq.last_reqnr,
        executed=seq.executed,
        duplicates=seq.duplicates,
        rejected=seq.rejected,
        vehicle_connected=service.vehicle.connected,
        vehicle_url=service.vehicle.url,
        position=await latest_position(service.vehicle),
        handovers=seq.handovers,
        master_connected=service.streams.master_connected,
        controllers=seq.controllers,
        vehicle=service.vehicle.link(),
        waiting="; ".join(
            filter(None, (service.waiting, service.store.problem if service.store else ""))
        ),
        waits=[w.to_proto() for w in service.waits]
        + (
            [Wait("state file", service.store.problem, 0.0).to_proto()]
            if service.store is not None and service.store.problem
            else []
        ),
        watermark_reqnr=seq.cache.watermark,
        reachable=[c for c in seq.ring if c in service.standby.reachable],
        takeover_after_s=service.takeover_after_s,
        preparing_for=seq.preparing.target if seq.preparing is not None else -1,
        preparing_lacks_bytes=(seq.preparing.lacks_bytes or 0) if seq.preparing else 0,
        handover_policy=drone_pb2.HANDOVER_POLICY_NONE,
    )
    if service.policy is not None:
        service.policy.fill_status(status)
    if service.core.failsafe is not None:
        status.failsafe.CopyFrom(failsafe_proto(service.core.failsafe))
    fill_status(status, service.operator)
    status.lost_link_s = service.core.safety.lost_link_s
    status.lost_link_action = service.core.safety.lost_link_action
    for what, bound in zip(("max_speed", "max_altitude"), service.core.bounds(), strict=True):
        status.bounds.add(bound=what, value=bound.value, name=bound.name, source=bound.source)
    links, clock = service.link_states(), time.monotonic()
    for cid in seq.ring:
        status.links.append(
            service.probes.status(
                cid,
                cid in service.standby.reachable,
                service.streams.connected(cid),
                links[cid].down_for_s,
                clock,
            )
        )
    status.retained_replies, status.retained_bytes = seq.cache.retained
    if service.vehicle.connected:
        try:
            status.flight_state.CopyFrom(
                await asyncio.wait_for(
                    service.vehicle.GetFlightState(api.GetFlightStateRequest()),
                    READ_TIMEOUT_S,
                )
            )
        except StatusError as err:  # unknown now: not ready, and why
            status.flight_state.not_ready_reason = err.message
        except TimeoutError:
            pass  # unknown now: left empty
    if service.store is not None:
        status.audit_oldest_reqnr = service.store.oldest_audit_reqnr()
    elif seq.audit:
        status.audit_oldest_reqnr = seq.audit[0].reqnr
    if include_audit:
        limit = min(audit_limit or AUDIT_PAGE, AUDIT_PAGE_MAX)
        if service.store is not None:
            page = service.store.audit_page(audit_after_reqnr, limit + 1)
        else:
            page = [e for e in seq.audit if e.reqnr > audit_after_reqnr][: limit + 1]
        status.audit_more = len(page) > limit
        status.audit.extend(page[:limit])
    return status
