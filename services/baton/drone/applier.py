"""The drone service's effect applier: ``DroneCore``'s effects carried out, in their order.

The order is the core's (``effects.py``): what it books is persisted before any
controller hears of it; a switch wakes the old master's Connect stream, which
asks ``connects.ConnectStream`` what to write; a TakeOver goes on the taker's
newest standby stream; notes go to the log. The service applies one event's
effects at a time, under its execution lock.
"""

from __future__ import annotations

import asyncio
from collections.abc import Iterable
from typing import TYPE_CHECKING

from baton.drone.effects import (
    Abandon,
    Book,
    DroneEffect,
    Preparing,
    SaveCounters,
    Switched,
    TellTakeOver,
    pins_policy,
)
from baton.drone.store import counters_of
from baton.rpc.labels import label
from baton.v1 import drone_pb2

if TYPE_CHECKING:
    from baton.drone.service import DroneService


class Applier:
    """Carries out the core's effects for one ``DroneService``."""

    def __init__(self, service: DroneService) -> None:
        self.service = service
        # Set (and replaced) at every switch: a prepared Handover call waits on it.
        self.switch_seen = asyncio.Event()

    def apply(self, effects: Iterable[DroneEffect], notice_delay_s: float = 0.0) -> None:
        """Carries out the core's effects in their order (``effects.py``), under the lock.
        ``notice_delay_s`` holds a switch's notice back (``Race``)."""
        service = self.service
        store, seq, log = service.store, service.seq, service.log
        for effect in effects:
            if isinstance(effect, Abandon):
                if store is not None:
                    store.abandon()
            elif isinstance(effect, Book):
                if store is not None:
                    served = effect.served
                    oldest = seq.cache.reqnrs[0]
                    store.served(counters_of(seq), served.cached, served.audit, oldest)
            elif isinstance(effect, SaveCounters):
                if store is not None:
                    store.save(counters_of(seq))
            elif isinstance(effect, Switched):
                self._switched(effect.record, notice_delay_s)
            elif isinstance(effect, Preparing):
                log.info(
                    "preparing a handover",
                    target=effect.notice.target,
                    timeout_s=effect.notice.timeout_s,
                    master_connected=service.streams.master_connected,
                )
                service.streams.wake(seq.master)
            elif isinstance(effect, TellTakeOver):
                self._tell_take_over(effect)
            else:
                (log.warning if effect.level == "warning" else log.info)(
                    effect.event, **effect.fields
                )

    def _switched(self, record: drone_pb2.HandoverRecord, notice_delay_s: float) -> None:
        """Logs a switch, pins the policy to a master the script or an operator chose, and
        wakes the old master's stream to carry the notice and a prepared Handover call."""
        service = self.service
        prepared = {}
        if record.prepare_started_at:
            prepared = {
                "prepared_s": round(record.decided_at - record.prepare_started_at, 6),
                "prepare_timed_out": record.prepare_timed_out,
                "lacked_bytes": record.prepare_lacked_bytes,
            }
        log = service.log.warning if record.prepare_timed_out else service.log.info
        log(
            "handover",
            old_master=record.old_master,
            new_master=record.new_master,
            after_reqnr=record.after_reqnr,
            epoch=record.epoch,
            trigger=label(drone_pb2.HandoverTrigger, record.trigger),
            kind=label(drone_pb2.HandoverKind, record.kind),
            old_master_connected=service.streams.connected(record.old_master),
            **prepared,
            reason=record.reason or None,
        )
        if service.policy is not None and pins_policy(record):
            service.policy.pin(record.new_master)
        service.streams.wake(record.old_master, notice_delay_s)
        self.switch_seen.set()
        self.switch_seen = asyncio.Event()

    def _tell_take_over(self, effect: TellTakeOver) -> None:
        service = self.service
        record, lost_at, cache = effect.record, effect.lost_at, service.seq.cache
        told = service.standby.tell(
            record.new_master, drone_pb2.StandbyEvent(take_over=effect.take_over)
        )
        retained, retained_bytes = cache.retained
        lost = record.trigger == drone_pb2.HANDOVER_TRIGGER_LOST
        service.log.warning(
            "master lost: taken over" if lost else "takeover",
            lost=record.old_master,
            new_master=record.new_master,
            epoch=record.epoch,
            unseen_s=round(record.decided_at - lost_at, 3) if lost_at else None,
            watermark_reqnr=cache.watermark,
            retained_replies=retained,
            retained_bytes=retained_bytes,
            told_on_standby=told,
        )
