"""Geofences for missions: areas (polygons of latitude and longitude, circles) a vehicle
stays inside (inclusion) or outside of (exclusion), and a ceiling in metres above home.

A point is inside a fence when it is inside every inclusion area, outside every
exclusion area and not above the ceiling. Every inclusion area, not any one of
them: ArduPilot breaches a vehicle outside any of its inclusion fences, PX4 only one
outside all of them, and a point inside all of them is inside on both. Polygons are
checked on the missions' flat projection around their first vertex (``geo.py``:
metres east and north), exact to centimetres over the few kilometres a fence spans;
a point on an edge counts as inside. A QGroundControl plan's ``geoFence`` is read
into these types (``baton.missions.plan``), and the drone enforces them
(``baton.drone.fence``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from baton.sdk.geo import north_east_m
from baton.sdk.types import Position


def _local(lat0: float, lon0: float, lat: float, lon: float) -> tuple[float, float]:
    """Metres east and north of (lat0, lon0) on the flat projection around it (the
    missions' own, ``baton.sdk.geo``)."""
    north, east = north_east_m(Position(lat0, lon0), Position(lat, lon))
    return east, north


@dataclass(frozen=True)
class FencePolygon:
    """A polygon of (latitude, longitude) vertices, in order, not repeating the first."""

    vertices: tuple[tuple[float, float], ...]
    inclusion: bool = True

    def _points(self) -> list[tuple[float, float]]:
        lat0, lon0 = self.vertices[0]
        return [_local(lat0, lon0, lat, lon) for lat, lon in self.vertices]

    def contains(self, latitude_deg: float, longitude_deg: float) -> bool:
        """Whether the point is inside the polygon or on its edge (ray casting)."""
        lat0, lon0 = self.vertices[0]
        x, y = _local(lat0, lon0, latitude_deg, longitude_deg)
        points = self._points()
        inside = False
        for (x1, y1), (x2, y2) in zip(points, points[1:] + points[:1], strict=True):
            if _on_segment(x, y, x1, y1, x2, y2):
                return True
            if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
                inside = not inside
        return inside

    def describe(self) -> str:
        kind = "inclusion" if self.inclusion else "exclusion"
        return f"the {kind} polygon of {len(self.vertices)} vertices"


@dataclass(frozen=True)
class FenceCircle:
    """A circle: its centre (latitude, longitude) and radius in metres."""

    latitude_deg: float
    longitude_deg: float
    radius_m: float
    inclusion: bool = True

    def contains(self, latitude_deg: float, longitude_deg: float) -> bool:
        x, y = _local(self.latitude_deg, self.longitude_deg, latitude_deg, longitude_deg)
        return math.hypot(x, y) <= self.radius_m

    def describe(self) -> str:
        kind = "inclusion" if self.inclusion else "exclusion"
        return (
            f"the {kind} circle of {self.radius_m:g} m around "
            f"({self.latitude_deg:.7f}, {self.longitude_deg:.7f})"
        )


@dataclass(frozen=True)
class Fence:
    """The mission's fence: its areas, its ceiling (metres above home) and what a breach
    makes the vehicle do (``rtl`` or ``land``: ``config.FenceConfig``)."""

    polygons: tuple[FencePolygon, ...] = ()
    circles: tuple[FenceCircle, ...] = ()
    ceiling_m: float = math.inf
    action: str = "rtl"

    @property
    def areas(self) -> tuple[FencePolygon | FenceCircle, ...]:
        return (*self.polygons, *self.circles)

    def outside(
        self, latitude_deg: float, longitude_deg: float, relative_altitude_m: float | None = None
    ) -> str | None:
        """Why the point is outside the fence ("outside the inclusion polygon of 4
        vertices", "45 m above home is above the ceiling of 40 m"); None if inside. An
        altitude of None is not checked."""
        for area in self.areas:
            if area.contains(latitude_deg, longitude_deg) != area.inclusion:
                where = "outside" if area.inclusion else "inside"
                return f"{where} {area.describe()}"
        if relative_altitude_m is not None and relative_altitude_m > self.ceiling_m:
            return (
                f"{relative_altitude_m:g} m above home is above the fence's ceiling of "
                f"{self.ceiling_m:g} m"
            )
        return None


# -- what a fence must be -----------------------------------------------------------


def polygon_problem(vertices: Sequence[Sequence[float]]) -> str | None:
    """What is wrong with a fence polygon, as a person fixes it; None if it can be
    flown: at least 3 distinct vertices, each [latitude, longitude] in range, edges that
    do not cross (a closing vertex repeating the first is allowed: see
    ``open_ring``)."""
    for k, vertex in enumerate(vertices):
        if len(vertex) != 2:
            return f"vertex {k} is {list(vertex)}: give each vertex as [latitude, longitude]"
        lat, lon = vertex
        if not (math.isfinite(lat) and math.isfinite(lon)) or abs(lat) > 90 or abs(lon) > 180:
            return (
                f"vertex {k} ({lat}, {lon}) is not a place: latitude in [-90, 90], "
                "longitude in [-180, 180]"
            )
    ring = open_ring([(float(v[0]), float(v[1])) for v in vertices])
    if len(set(ring)) < 3:
        return (
            f"a fence polygon needs at least 3 distinct vertices, it has {len(set(ring))}; "
            "list the corners of the area in order"
        )
    lat0, lon0 = ring[0]
    points = [_local(lat0, lon0, lat, lon) for lat, lon in ring]
    n = len(points)
    for i in range(n):
        for j in range(i + 1, n):
            if j == i + 1 or (i == 0 and j == n - 1):
                continue  # neighbours share a vertex
            a, b = points[i], points[(i + 1) % n]
            c, d = points[j], points[(j + 1) % n]
            if _segments_cross(a, b, c, d):
                return (
                    f"edges {i}-{(i + 1) % n} and {j}-{(j + 1) % n} cross: the polygon "
                    "intersects itself; list its vertices in order around the area"
                )
    if abs(_area(points)) < 1.0:
        return "the polygon encloses no area (its vertices lie on a line); list its corners"
    return None


def open_ring(vertices: Sequence[tuple[float, float]]) -> tuple[tuple[float, float], ...]:
    """The vertices without a last one that repeats the first (GeoJSON closes its rings
    that way; QGroundControl does not)."""
    ring = tuple(vertices)
    return ring[:-1] if len(ring) > 1 and ring[0] == ring[-1] else ring


def outside_points(
    fence: Fence, points: Sequence[tuple[str, float, float, float | None]]
) -> list[str]:
    """One line for each named point (name, latitude, longitude, altitude above home or
    None) outside ``fence``, saying why."""
    lines = []
    for name, lat, lon, alt in points:
        why = fence.outside(lat, lon, alt)
        if why is not None:
            lines.append(f"{name} ({lat:.7f}, {lon:.7f}) is {why}")
    return lines


def _on_segment(x: float, y: float, x1: float, y1: float, x2: float, y2: float) -> bool:
    """Whether (x, y) lies on the segment within a centimetre."""
    length = math.hypot(x2 - x1, y2 - y1)
    if length == 0:
        return math.hypot(x - x1, y - y1) <= 0.01
    cross = abs((x2 - x1) * (y - y1) - (y2 - y1) * (x - x1)) / length
    dot = (x - x1) * (x2 - x1) + (y - y1) * (y2 - y1)
    return cross <= 0.01 and -0.01 * length <= dot <= length * length + 0.01 * length


def _segments_cross(
    a: tuple[float, float], b: tuple[float, float], c: tuple[float, float], d: tuple[float, float]
) -> bool:
    """Whether segments ab and cd share a point (touching counts)."""

    def orient(p: tuple[float, float], q: tuple[float, float], r: tuple[float, float]) -> float:
        return (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0])

    def between(p: tuple[float, float], q: tuple[float, float], r: tuple[float, float]) -> bool:
        return min(p[0], q[0]) <= r[0] <= max(p[0], q[0]) and min(p[1], q[1]) <= r[1] <= max(
            p[1], q[1]
        )

    d1, d2, d3, d4 = orient(c, d, a), orient(c, d, b), orient(a, b, c), orient(a, b, d)
    if ((d1 > 0) != (d2 > 0)) and ((d3 > 0) != (d4 > 0)) and d1 and d2 and d3 and d4:
        return True
    return (
        (d1 == 0 and between(c, d, a))
        or (d2 == 0 and between(c, d, b))
        or (d3 == 0 and between(a, b, c))
        or (d4 == 0 and between(a, b, d))
    )


def _area(points: Sequence[tuple[float, float]]) -> float:
    """The signed area (shoelace), square metres."""
    return 0.5 * sum(
        x1 * y2 - x2 * y1
        for (x1, y1), (x2, y2) in zip(points, [*points[1:], points[0]], strict=True)
    )
