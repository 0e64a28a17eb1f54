"""The mission's geofence at the drone, as pure decisions: whether a call asks the
vehicle out of the fence, whether the vehicle is out of it (a breach).

No clock, no I/O; the fence itself and what it must be are ``baton.sdk.fence``'s.
``DroneCore`` asks ``move_refusal`` for every admitted call (a Goto outside, a Takeoff
above the ceiling: refused before execution, booked like the other refusals) and
``breach`` for the vehicle's telemetry position (the failsafe with the fence's
action, ``safety.fence_failsafe``); the configuration asks ``polygon_problem`` and
``outside`` to refuse a fence that cannot be flown (docs/operating.md, "The safety
net").
"""

from __future__ import annotations

import grpc
from google.protobuf.message import Message

from baton.rpc.errors import StatusError
from baton.sdk.fence import Fence
from baton.v1 import drone_api_pb2 as api


def move_refusal(method: str, request: Message, fence: Fence | None) -> StatusError | None:
    """OUT_OF_RANGE for a call that would move the vehicle out of ``fence``: a Goto to a
    point outside it, a Takeoff above its ceiling; None otherwise (or without a fence).
    A Goto without a latitude or longitude is left to the execution, which refuses it."""
    if fence is None:
        return None
    if isinstance(request, api.TakeoffRequest):
        # Takes off where it is (inside: it was armed there, the drone checks the home
        # against the fence); only the altitude can leave it.
        if request.altitude_m <= fence.ceiling_m:
            return None
        target = f"{request.altitude_m:g} m above home"
        why: str | None = f"above its ceiling of {fence.ceiling_m:g} m"
    elif isinstance(request, api.GotoRequest):
        if not (request.HasField("latitude_deg") and request.HasField("longitude_deg")):
            return None
        why = fence.outside(
            request.latitude_deg, request.longitude_deg, request.relative_altitude_m
        )
        if why is None:
            return None
        target = (
            f"({request.latitude_deg:.7f}, {request.longitude_deg:.7f}, "
            f"{request.relative_altitude_m:g} m)"
        )
    else:
        return None
    return StatusError(
        grpc.StatusCode.OUT_OF_RANGE,
        f"{method} to {target} is outside the mission's fence ({why}); nothing was executed",
    )


def breach(fence: Fence | None, position: api.Position) -> str | None:
    """Why the vehicle at ``position`` (its telemetry) is out of ``fence``; None while it
    is inside, without a fence, or while its position is not known (all zero)."""
    if fence is None or not (position.latitude_deg or position.longitude_deg):
        return None
    return fence.outside(
        position.latitude_deg, position.longitude_deg, position.relative_altitude_m
    )
