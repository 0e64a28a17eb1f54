"""Photograph a list of waypoints: what the grid and the corridor missions share.

Wait until the vehicle is ready to arm, take off to ``altitude_m``, fly to
each waypoint (metres north and east of the take-off point) at ``speed_m_s``,
polling the position every ``poll_s`` seconds, take a picture at each, and
land.

Where the waypoints are: they are laid out from the vehicle's position read
just before arming, on the ground. That is where ArduPilot and PX4 put home
when they arm, whereas a home read earlier can be elsewhere (ArduPilot's
boot-time home is wherever its first GPS fix was). The speed is set once
airborne: ArduCopter refuses a speed change before takeoff, and the drone
service re-applies it after every goto (ArduCopter resets it at each
reposition).
"""

from __future__ import annotations

from collections.abc import Sequence

from baton.sdk import Drone, distance_m, offset


def wait_until_ready(drone: Drone, poll_s: float) -> None:
    """Polls until the vehicle can be armed, saying why not whenever the reason changes."""
    said = ""
    while not (state := drone.mobility.flight_state()).ready:
        if state.not_ready_reason != said:
            said = state.not_ready_reason
            print(f"waiting for the vehicle: {said}", flush=True)
        drone.clock.sleep(poll_s)


def survey(
    drone: Drone,
    targets: Sequence[tuple[float, float]],
    altitude_m: float,
    speed_m_s: float,
    poll_s: float,
    arrive_m: float,
) -> None:
    """Flies to every (north, east) target in order and photographs it."""
    wait_until_ready(drone, poll_s)
    origin = drone.mobility.position()
    drone.mobility.arm()
    drone.mobility.takeoff(altitude_m)
    while drone.mobility.position().relative_altitude_m < altitude_m - 0.5:
        drone.clock.sleep(poll_s)
    drone.mobility.set_speed(speed_m_s)
    for k, (north, east) in enumerate(targets, start=1):
        target = offset(origin, north, east)
        drone.mobility.goto(target, relative_altitude_m=altitude_m)
        while distance_m(drone.mobility.position(), target) > arrive_m:
            drone.clock.sleep(poll_s)
        picture = drone.camera.take_picture()
        if distance_m(picture.position, target) > 2 * arrive_m:
            raise RuntimeError(f"picture {picture.sequence} taken away from waypoint {k}")
        print(
            f"waypoint {k} of {len(targets)}: picture {picture.sequence} "
            f"({len(picture.image)} bytes)",
            flush=True,
        )
    drone.mobility.land()
    while drone.mobility.flight_state().in_air:
        drone.clock.sleep(poll_s)
    print("mission complete", flush=True)
