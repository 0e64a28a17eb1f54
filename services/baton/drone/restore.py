"""A drone service's start from its state file: what ``DroneCore.restarted`` resumes from.

I/O only: the store is read (counters, replies, audit, the request a restart
cut off, the commanded state, a failsafe), the vehicle is given back the
cruise speed the mission set, and the core decides the rest (``Kept.of``,
``DroneCore.restarted``); its effects are applied as a served request's are.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from baton.drone.core import Kept
from baton.drone.invocations import SPEED_KEY
from baton.drone.store import DroneStore, counters_of

if TYPE_CHECKING:
    from baton.drone.service import DroneService

# The durable commanded state's key of what the drone last commanded the vehicle
# (DroneCore.kept_command).
VEHICLE_COMMAND_KEY = "vehicle_command"


def restore(service: DroneService, store: DroneStore) -> None:
    """Resumes ``service`` from ``store`` (``DroneCore.restarted``): master, counters,
    replies, audit, script, the vehicle's commanded state, a failsafe, a request cut off;
    a new file is started with the sequencer's state."""
    state, log = store.load(), service.log
    if state is None:
        store.save(counters_of(service.seq))
        log.info("new state file", path=str(store.path))
        return
    commanded = store.load_commanded()
    speed = commanded.get(SPEED_KEY)
    if speed is not None:
        service.vehicle.restore_speed(float(speed))
        log.info("cruise speed restored", speed_m_s=speed)
    failsafe = store.load_failsafe()
    if failsafe is not None:
        log.warning("still in failsafe", cause=failsafe.cause, reason=failsafe.reason)
    service.operator.restore()
    cut = service.cut_off = state.executing
    kept = Kept.of(state, commanded.get(VEHICLE_COMMAND_KEY), failsafe)
    effects = service.core.restarted(time.time(), kept)
    service.saved_command = service.core.kept_command()
    c, seq = state.counters, service.seq
    log.info(
        "state resumed",
        path=str(store.path),
        master=c.master,
        epoch=seq.epoch,
        last_reqnr=c.last_reqnr,
        cached_replies=len(state.replies),
        audit=len(state.audit),
        script_left=len(seq.script),
    )
    service.invocations.served(0 if cut is None else cut.reqnr, effects)
