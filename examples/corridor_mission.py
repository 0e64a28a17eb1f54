"""A corridor survey, as a mission file: a line of waypoints with a picture at each.

    baton controller --id 0 --config examples/corridor.yaml \
        --mission examples/corridor_mission.py --mission-arg length_m=1500

The mission lives in ``baton.missions.corridor`` so that the testbed runs the
very same code.
"""

from baton.missions.corridor import mission, waypoints

__all__ = ["mission", "waypoints"]
