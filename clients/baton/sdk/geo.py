"""Small geodesy for missions: offsets and distances on a local flat Earth.

Good to centimetres over a few kilometres, which is the scale of a mission
flown from one take-off point.
"""

from __future__ import annotations

import math

from baton.sdk.types import Position

EARTH_RADIUS_M = 6_378_137.0


def offset(origin: Position, north_m: float, east_m: float, up_m: float = 0.0) -> Position:
    """The position ``north_m`` north and ``east_m`` east of ``origin``."""
    dlat = math.degrees(north_m / EARTH_RADIUS_M)
    dlon = math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(origin.latitude_deg))))
    return Position(
        origin.latitude_deg + dlat,
        origin.longitude_deg + dlon,
        origin.absolute_altitude_m + up_m,
        origin.relative_altitude_m + up_m,
    )


def distance_m(a: Position, b: Position) -> float:
    """Horizontal distance between two positions, metres."""
    north = math.radians(b.latitude_deg - a.latitude_deg) * EARTH_RADIUS_M
    east = (
        math.radians(b.longitude_deg - a.longitude_deg)
        * EARTH_RADIUS_M
        * math.cos(math.radians((a.latitude_deg + b.latitude_deg) / 2))
    )
    return math.hypot(north, east)


def north_east_m(origin: Position, point: Position) -> tuple[float, float]:
    """Metres north and east of ``origin`` to ``point``: the inverse of ``offset``."""
    north = math.radians(point.latitude_deg - origin.latitude_deg) * EARTH_RADIUS_M
    east = (
        math.radians(point.longitude_deg - origin.longitude_deg)
        * EARTH_RADIUS_M
        * math.cos(math.radians(origin.latitude_deg))
    )
    return north, east
