"""Asks for a speed and a sleep no vehicle can fly, and a speed under the configuration's
bound but over the vehicle's own (each refused with the bound named), then flies a
short leg at a sane speed and lands."""

from __future__ import annotations

import grpc

from baton.sdk import Drone, DroneCallError


def mission(drone: Drone) -> None:
    """SetSpeed(1e9), SetSpeed(10) and Sleep(1e12) refused INVALID_ARGUMENT; the mission
    goes on."""
    drone.mobility.arm()
    drone.mobility.takeoff(5.0)
    for call in (
        lambda: drone.mobility.set_speed(1e9),
        lambda: drone.mobility.set_speed(10.0),
        lambda: drone.clock.sleep(1e12),
    ):
        try:
            call()
        except DroneCallError as err:
            assert err.code is grpc.StatusCode.INVALID_ARGUMENT, err
            assert " is beyond " in err.details and "bound" in err.details, err
            print(f"refused: {err}", flush=True)
        else:
            raise AssertionError("a call beyond the vehicle's bounds was accepted")
    drone.clock.sleep(5.0)  # in the air: a speed is sent to a flying vehicle only
    drone.mobility.set_speed(3.0)
    drone.mobility.land()
