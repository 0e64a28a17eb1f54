"""The safety net's watch in the drone service: a look at the vehicle every tick.

A driver of ``DroneCore.failsafe_check`` (docs/operating.md, "The safety net"):
each tick it reads the vehicle's flight state and position, asks the core which
failsafe is due, and under the execution lock (asked again there: a request may
have come meanwhile) books it in the core and the store before it commands the
vehicle, so a request that comes next is refused whatever the vehicle answers.
A nearest_station failsafe lands once the vehicle is over its station.
"""

from __future__ import annotations

import asyncio
import time
from typing import TYPE_CHECKING

from baton.drone.core import WATCH_TICK_S
from baton.drone.mobility_api import READ_TIMEOUT_S, command_action, latest_position
from baton.drone.safety import LAND, Failsafe, landing_due, mode_seen, nearest_station
from baton.rpc.errors import StatusError
from baton.v1 import drone_api_pb2 as api

if TYPE_CHECKING:
    from baton.drone.service import DroneService


class FailsafeWatch:
    """The failsafe watch of one ``DroneService``."""

    def __init__(self, service: DroneService) -> None:
        self.service = service
        # The nearest_station failsafe whose landing was commanded (at most once).
        self._landing_for: Failsafe | None = None

    async def run(self) -> None:
        """Puts the vehicle in failsafe when ``DroneCore.failsafe_check`` says so, and lands
        it at the station once a nearest_station failsafe has brought it there."""
        service = self.service
        while True:
            limits = service.vehicle.autopilot_limits()
            if limits is not None:
                service.core.limits_read(limits)
            state = await self.flight_state()
            if state is None:
                service.core.vehicle_unseen()
            else:
                here = await latest_position(service.vehicle)
                failsafe = service.core.failsafe
                if failsafe is not None and failsafe.station is not None and state.in_air:
                    await self._land_at_station(failsafe, here)
                else:
                    due = self.due(state, here)
                    if due is not None:
                        async with service.execution_lock:
                            # Re-checked under the lock: a request may have come meanwhile.
                            due = self.due(state, here)
                            if due is not None:
                                await self.enter(due)
            await asyncio.sleep(WATCH_TICK_S)

    async def flight_state(self) -> api.GetFlightStateReply | None:
        """The vehicle's flight state now; None while it is not connected or does not say."""
        service = self.service
        if not service.vehicle.connected:
            return None
        try:
            return await asyncio.wait_for(
                service.vehicle.GetFlightState(api.GetFlightStateRequest()), READ_TIMEOUT_S
            )
        except (StatusError, TimeoutError):
            return None

    def due(self, state: api.GetFlightStateReply, here: api.Position) -> Failsafe | None:
        """``DroneCore.failsafe_check`` with the vehicle's flight state and position, who
        holds a stream now, who is in range, and the station nearest the vehicle."""
        service = self.service
        nearest = nearest_station(here, service.stations)
        due = service.sight().failsafe_check(
            service.core,
            time.time(),
            state.in_air,
            state.battery_percent,
            here,
            mode_seen(state),
            nearest,
        )
        service.keep_command()  # the vehicle seen in the air since the command
        return due

    async def enter(self, failsafe: Failsafe) -> None:
        """Puts the vehicle in ``failsafe`` (the caller holds the lock): booked in the core
        and the store first, so a request that comes next is refused whatever the
        vehicle answers, then the action commanded."""
        service = self.service
        service.core.enter_failsafe(failsafe)
        service.save_failsafe()
        service.log.warning(
            "failsafe",
            cause=failsafe.cause,
            action=failsafe.action,
            station=failsafe.station,
            reason=failsafe.reason,
        )
        if not failsafe.drone_acts:
            return  # the autopilot flies the vehicle (or a pilot does)
        try:
            await self._command(failsafe)
        except StatusError as err:
            service.log.error("failsafe action refused by the vehicle", reason=err.message)

    async def _command(self, failsafe: Failsafe) -> None:
        service = self.service
        vehicle = service.vehicle
        if await command_action(vehicle, failsafe.action):
            return
        if failsafe.station is not None:
            here = await latest_position(vehicle)
            at = service.stations[failsafe.station].location
            await vehicle.Goto(
                api.GotoRequest(
                    latitude_deg=at.latitude_deg,
                    longitude_deg=at.longitude_deg,
                    relative_altitude_m=max(here.relative_altitude_m, 1.0),
                )
            )

    async def _land_at_station(self, failsafe: Failsafe, here: api.Position) -> None:
        """Lands once a nearest_station failsafe has brought the vehicle over its station
        (``safety.landing_due``); once: the vehicle landing is no longer flying there."""
        service = self.service
        assert failsafe.station is not None
        station = service.stations[failsafe.station]
        if failsafe is self._landing_for or not landing_due(here, station):
            return
        async with service.execution_lock:
            if service.core.failsafe is failsafe:
                self._landing_for = failsafe
                service.log.warning("failsafe: landing at the station", station=station.id)
                try:
                    service.core.commanding(LAND, time.time())
                    await service.vehicle.Land(api.LandRequest())
                    service.commanded(LAND)
                except StatusError as err:
                    self._landing_for = None  # tried again at the next look
                    service.log.error("failsafe landing refused by the vehicle", reason=err.message)
