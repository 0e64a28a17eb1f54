"""A mission that gives up on a TakePicture (a short deadline), then takes it again.

The drone link's latency makes the deadline pass while the drone is at it:
the drone takes that picture and records it; the master logs the call as the
deadline failure the program saw, so the replicas see it too; the second
TakePicture is a new request.
"""

import os

import grpc

from baton.rpc.channels import sync_channel
from baton.rpc.mission import MISSION_TOKEN_ENV, MISSION_TOKEN_METADATA
from baton.sdk import Drone
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_api_pb2_grpc


def mission(drone: Drone, deadline_s: float = 0.45) -> None:
    drone.mobility.position()
    camera = drone_api_pb2_grpc.CameraStub(sync_channel(drone.address))
    as_program = ((MISSION_TOKEN_METADATA, os.environ[MISSION_TOKEN_ENV]),)
    try:
        camera.TakePicture(api.TakePictureRequest(), timeout=float(deadline_s), metadata=as_program)
        print("first picture: reply", flush=True)
    except grpc.RpcError as exc:
        print(f"first picture: {exc.code().name}", flush=True)
    drone.camera.take_picture()
    drone.mobility.position()
