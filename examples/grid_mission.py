"""The paper's grid mission (Section 5.3), as a mission file.

    baton controller --id 0 --config testbed.yaml --mission examples/grid_mission.py \
        --mission-arg grid=3 --mission-arg spacing_m=20

The mission itself lives in ``baton.missions.grid`` so that the testbed and
the benchmarks run the very same code; this file is what a mission author
would write: one function, ``mission(drone, **params)``.
"""

from baton.missions.grid import mission, waypoints

__all__ = ["mission", "waypoints"]
