"""The sim vehicle's side of a fence upload: the part of the MAVLink mission protocol
(https://mavlink.io/en/services/mission.html) that MAVSDK's Geofence plugin uses,
for ``MAV_MISSION_TYPE_FENCE``.

The ground station sends MISSION_COUNT; the vehicle asks for each item in turn with
MISSION_REQUEST_INT and the ground station answers with MISSION_ITEM_INT; after the
last, the vehicle decodes the items into a fence and answers MISSION_ACK (ACCEPTED,
or why not). MISSION_CLEAR_ALL of the fence type clears it. The fence held changes
only when a whole upload was accepted, as on an autopilot: a half-finished upload
leaves the fence it had. A copy of an item already received (its request answered
twice) is taken again; an item out of order is refused with MAV_MISSION_INVALID_SEQUENCE
and the upload ends, and so does a new MISSION_COUNT (the ground station began
again). Pure: ``SimVehicle`` sends what it returns and records the fence held.

Fence items (MAV_CMD): ``NAV_FENCE_POLYGON_VERTEX_INCLUSION`` (5001) and
``_EXCLUSION`` (5002), ``param1`` the polygon's vertex count, one item per vertex in
order; ``NAV_FENCE_CIRCLE_INCLUSION`` (5003) and ``_EXCLUSION`` (5004), ``param1``
the radius in metres; ``x``, ``y`` latitude and longitude times 1e7.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from baton.sdk.fence import Fence, FenceCircle, FencePolygon

FENCE = mavlink.MAV_MISSION_TYPE_FENCE
VERTEX = {
    mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION: True,
    mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION: False,
}
CIRCLE = {
    mavlink.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION: True,
    mavlink.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION: False,
}
# The most items a fence upload may hold (PX4's and ArduPilot's limits are of this order).
MAX_ITEMS = 256


@dataclass(frozen=True)
class Request:
    """Ask the ground station for item ``seq`` (MISSION_REQUEST_INT)."""

    seq: int


@dataclass(frozen=True)
class Ack:
    """End the transfer with MISSION_ACK ``result``; ``fence`` is the fence now held when
    an upload was accepted (None: unchanged), ``cleared`` when a clear was."""

    result: int
    fence: Fence | None = None
    cleared: bool = False


@dataclass
class FenceUpload:
    """One ground station's fence upload in progress (``count`` items, ``items`` so far)."""

    count: int = 0
    items: list[Any] = field(default_factory=list)
    active: bool = False

    def on_count(self, count: int) -> Request | Ack:
        """MISSION_COUNT: a new upload of ``count`` items (an upload under way is dropped)."""
        self.active, self.items = False, []
        if count > MAX_ITEMS:
            return Ack(mavlink.MAV_MISSION_NO_SPACE)
        if count == 0:
            return Ack(mavlink.MAV_MISSION_ACCEPTED, fence=Fence())
        self.count, self.active = count, True
        return Request(0)

    def on_item(self, item: Any) -> Request | Ack | None:
        """MISSION_ITEM_INT ``item``: ask for the next, or end; None: no upload under way
        (a late copy after the end: ignored)."""
        if not self.active:
            return None
        seq = item.seq
        if seq == len(self.items) - 1:
            self.items[-1] = item  # a copy of the last: its request was answered twice
            return Request(len(self.items))
        if seq != len(self.items):
            self.active = False
            return Ack(mavlink.MAV_MISSION_INVALID_SEQUENCE)
        self.items.append(item)
        if len(self.items) < self.count:
            return Request(len(self.items))
        self.active = False
        decoded = decode(self.items)
        if isinstance(decoded, int):
            return Ack(decoded)
        return Ack(mavlink.MAV_MISSION_ACCEPTED, fence=decoded)

    def on_clear(self) -> Ack:
        """MISSION_CLEAR_ALL of the fence type."""
        self.active, self.items = False, []
        return Ack(mavlink.MAV_MISSION_ACCEPTED, cleared=True)


def decode(items: list[Any]) -> Fence | int:
    """The fence the items describe, or the MAV_MISSION_RESULT refusing them."""
    polygons: list[FencePolygon] = []
    circles: list[FenceCircle] = []
    k = 0
    while k < len(items):
        item = items[k]
        if item.command in CIRCLE:
            if not item.param1 > 0:
                return int(mavlink.MAV_MISSION_INVALID_PARAM1)
            circles.append(
                FenceCircle(item.x / 1e7, item.y / 1e7, float(item.param1), CIRCLE[item.command])
            )
            k += 1
        elif item.command in VERTEX:
            n = int(item.param1)
            group = items[k : k + n]
            if n < 3 or len(group) < n or any(i.command != item.command for i in group):
                return int(mavlink.MAV_MISSION_INVALID_PARAM1)
            vertices = tuple((i.x / 1e7, i.y / 1e7) for i in group)
            polygons.append(FencePolygon(vertices, VERTEX[item.command]))
            k += n
        else:
            return int(mavlink.MAV_MISSION_UNSUPPORTED)
    return Fence(tuple(polygons), tuple(circles))
