"""A mission with a short deadline on every GetPosition, and a flush limit that holds the log.

On the master each GetPosition is answered at once. A replica gets the
entries only when the master flushes (at the end, 2 s later, with a large
flush limit),
so its program's deadlines pass while it waits: the program gave up on calls
the master's program did not. The replica restarts its program, which
replays the log from the start (node.py ``_replay_again``); before, the
mission stopped there with a determinism error.
"""

import os
import time

import grpc

from baton.rpc.channels import sync_channel
from baton.rpc.mission import MISSION_TOKEN_ENV, MISSION_TOKEN_METADATA
from baton.sdk import Drone
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_api_pb2_grpc


def mission(drone: Drone, deadline_s: float = 0.5) -> None:
    mobility = drone_api_pb2_grpc.MobilityStub(sync_channel(drone.address))
    as_program = ((MISSION_TOKEN_METADATA, os.environ[MISSION_TOKEN_ENV]),)
    for k in range(3):
        try:
            mobility.GetPosition(
                api.GetPositionRequest(), timeout=float(deadline_s), metadata=as_program
            )
            print(f"position {k}: reply", flush=True)
        except grpc.RpcError as exc:
            print(f"position {k}: {exc.code().name}", flush=True)
    time.sleep(2.0)  # the master flushes only after this: a replica's deadlines pass meanwhile
    drone.camera.take_picture()
