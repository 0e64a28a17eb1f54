"""A mission that is NOT deterministic: its request depends on which controller runs it."""

from baton.sdk import Drone


def mission(drone: Drone) -> None:
    drone.mobility.position()
    port = int(drone.address.rsplit(":", 1)[1])
    drone.camera.set_resolution(16 + port % 1000, 16)  # differs on every replica
    drone.mobility.position()
