"""A benchmark mission: a fixed sequence of drone calls with no flight and no polling loop.

The sequence is the ``script`` parameter, comma-separated steps:

- ``p``: read the position (a small entry in the log);
- ``c``: take a picture (about 1 MB at the default resolution);
- ``rWxH``: set the camera resolution to W x H pixels (picture size W*H*3 bytes);
- ``sX``: sleep X mission seconds (answered and logged by the controller, not
  sent to the drone);
- ``hX``: hold X seconds in the program itself, no call and nothing logged:
  the program stays running, so its controller logs calls as during a
  mission, while another caller (``baton bench micro``) calls in its place;
- ``STEP*N``: the step N times.

Every step is one request number, so the benchmarks can
compute offline where the master's log flushes (``baton.bench.script``) and
script the drone's handovers at exact request numbers.
"""

from __future__ import annotations

import time

from baton.sdk import Drone


def mission(drone: Drone, script: str = "p") -> None:
    """Runs the calls of ``script`` in order."""
    for token in filter(None, (t.strip() for t in script.split(","))):
        step, _, times = token.partition("*")
        for _ in range(int(times or 1)):
            if step == "p":
                drone.mobility.position()
            elif step == "c":
                drone.camera.take_picture()
            elif step.startswith("r"):
                width, _, height = step[1:].partition("x")
                drone.camera.set_resolution(int(width), int(height))
            elif step.startswith("s"):
                drone.clock.sleep(float(step[1:]))
            elif step.startswith("h"):
                time.sleep(float(step[1:]))
            else:
                raise ValueError(f"bench script step {token!r} is not p, c, rWxH, sX, hX or STEP*N")
    print("bench mission complete", flush=True)
