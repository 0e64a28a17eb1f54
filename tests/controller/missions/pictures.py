"""A mission that only takes pictures: ``count`` of them, each about 1 MB, on the ground.

Every picture is a log entry of about 1 MB that crosses the whole ring, so a
controller that kept every log message in memory would grow by ``count`` MB
(issue 9, defect 8).
"""

from baton.sdk import Drone


def mission(drone: Drone, count: int = 200) -> None:
    for k in range(1, int(count) + 1):
        picture = drone.camera.take_picture()
        if picture.sequence != k:
            raise RuntimeError(f"picture {k} came back as sequence {picture.sequence}")
    print(f"{count} pictures taken", flush=True)
