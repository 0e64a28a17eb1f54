"""The flight on a map: its path, each station's range, the master along the path,
each handover with its delay and reason, and where each picture was taken; as GeoJSON
(QGIS, geojson.io) and a PNG.

``Track`` collects the vehicle's position and the drone's master from the
testbed's snapshots (twice a second); ``flight_geojson`` turns the track, the
testbed file and the report into one FeatureCollection, with simplestyle
properties (``stroke``, ``fill``, ``marker-color``) so that geojson.io
colours each master's part of the path and its station alike;
``draw_flight`` draws the same collection with matplotlib, in metres east
and north of the first point, and says where on the picture each of the
pictures was taken (the HTML report puts their thumbnails there).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

from baton.config import BatonConfig
from baton.sdk import Position, offset
from baton.sdk.geo import north_east_m
from baton.testbed.local import Snapshot
from baton.v1 import drone_pb2

# One colour per controller (matplotlib's tab10), by id.
PALETTE = (
    "#1f77b4",
    "#ff7f0e",
    "#2ca02c",
    "#d62728",
    "#9467bd",
    "#8c564b",
    "#e377c2",
    "#7f7f7f",
    "#bcbd22",
    "#17becf",
)
# Vertices of a range circle.
CIRCLE_VERTICES = 72


def colour(controller_id: int) -> str:
    """The controller's colour on the map."""
    return PALETTE[controller_id % len(PALETTE)]


@dataclass(frozen=True)
class TrackPoint:
    """Where the vehicle was, when (Unix seconds) and who was master."""

    time: float
    latitude_deg: float
    longitude_deg: float
    master: int


class Track:
    """The flight path, from the snapshots the testbed takes while the mission runs."""

    def __init__(self) -> None:
        self.points: list[TrackPoint] = []

    def __call__(self, snapshot: Snapshot, now: float) -> None:
        """Notes the vehicle's position (skipped while unknown: all zero)."""
        self.note(snapshot.drone, now)

    def note(self, drone: drone_pb2.DroneStatus, now: float) -> None:
        """Notes where the drone's status says the vehicle is (skipped while unknown)."""
        here = drone.position
        if here.latitude_deg == 0 and here.longitude_deg == 0:
            return
        self.points.append(TrackPoint(now, here.latitude_deg, here.longitude_deg, drone.master))


def _lon_lat(latitude_deg: float, longitude_deg: float) -> list[float]:
    return [round(longitude_deg, 7), round(latitude_deg, 7)]  # GeoJSON: longitude first


def _circle(centre: Position, radius_m: float) -> list[list[float]]:
    ring = []
    for k in range(CIRCLE_VERTICES + 1):
        angle = 2 * math.pi * k / CIRCLE_VERTICES
        point = offset(centre, radius_m * math.cos(angle), radius_m * math.sin(angle))
        ring.append(_lon_lat(point.latitude_deg, point.longitude_deg))
    return ring


def _segments(points: Sequence[TrackPoint]) -> list[tuple[int, list[TrackPoint]]]:
    """The path cut where the master changes (each part starts where the last ended)."""
    segments: list[tuple[int, list[TrackPoint]]] = []
    for point in points:
        if segments and segments[-1][0] == point.master:
            segments[-1][1].append(point)
            continue
        start = [segments[-1][1][-1]] if segments else []
        segments.append((point.master, [*start, point]))
    return segments


def _handover_point(handover: dict[str, Any], points: Sequence[TrackPoint]) -> list[float] | None:
    """Where a handover was decided: the policy's own position, else the track's
    point nearest in time to the drone's decision."""
    if handover.get("position"):
        latitude, longitude = handover["position"]
        return _lon_lat(latitude, longitude)
    decided = handover.get("decided_at")
    if not points or not decided:
        return None
    nearest = min(points, key=lambda p: abs(p.time - decided))
    return _lon_lat(nearest.latitude_deg, nearest.longitude_deg)


def flight_geojson(
    config: BatonConfig,
    report: dict[str, Any],
    points: Sequence[TrackPoint],
    pictures: Sequence[dict[str, Any]] = (),
) -> dict[str, Any]:
    """The run as a GeoJSON FeatureCollection: stations and their ranges, the path by
    master, the handovers (delay, reason, trigger, kind), and the pictures (the camera's
    effects lines, ``baton.effects``: those that say where they were taken)."""
    features: list[dict[str, Any]] = []
    for c in config.controllers:
        if c.location is None:
            continue
        where = Position(c.location.latitude_deg, c.location.longitude_deg)
        style = {"controller": c.id, "marker-color": colour(c.id)}
        features.append(
            {
                "type": "Feature",
                "geometry": {
                    "type": "Point",
                    "coordinates": _lon_lat(where.latitude_deg, where.longitude_deg),
                },
                "properties": {"kind": "station", "range_m": c.range_m, **style},
            }
        )
        if c.range_m is not None:
            features.append(
                {
                    "type": "Feature",
                    "geometry": {"type": "Polygon", "coordinates": [_circle(where, c.range_m)]},
                    "properties": {
                        "kind": "range",
                        "controller": c.id,
                        "range_m": c.range_m,
                        "stroke": colour(c.id),
                        "fill": colour(c.id),
                        "fill-opacity": 0.08,
                    },
                }
            )
    for master, segment in _segments(points):
        features.append(
            {
                "type": "Feature",
                "geometry": {
                    "type": "LineString",
                    "coordinates": [_lon_lat(p.latitude_deg, p.longitude_deg) for p in segment],
                },
                "properties": {
                    "kind": "path",
                    "master": master,
                    "stroke": colour(master),
                    "stroke-width": 3,
                },
            }
        )
    for k, handover in enumerate(report["handovers"], start=1):
        at = _handover_point(handover, points)
        if at is None:
            continue
        features.append(
            {
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": at},
                "properties": {
                    "kind": "handover",
                    "number": k,
                    "from": handover["from"],
                    "to": handover["to"],
                    "after_reqnr": handover["after_reqnr"],
                    "delay_s": handover["delay_s"],
                    "trigger": handover["trigger"],
                    "handover_kind": handover["kind"],
                    "reason": handover.get("reason") or handover["trigger"],
                    "marker-color": colour(handover["to"]),
                    "marker-symbol": "star",
                },
            }
        )
    for picture in pictures:
        if picture.get("effect") != "picture" or "latitude_deg" not in picture:
            continue
        features.append(
            {
                "type": "Feature",
                "geometry": {
                    "type": "Point",
                    "coordinates": _lon_lat(picture["latitude_deg"], picture["longitude_deg"]),
                },
                "properties": {
                    "kind": "picture",
                    "seq": picture["seq"],
                    "time": picture["time"],
                    "marker-color": "#555555",
                    "marker-symbol": "camera",
                    "marker-size": "small",
                },
            }
        )
    return {"type": "FeatureCollection", "features": features}


def draw_flight(
    geojson: dict[str, Any], path: Path | BinaryIO, title: str
) -> dict[int, tuple[float, float]]:
    """The collection as a PNG, metres east and north of the path's first point (to a
    file, or a binary stream). Returns where each picture is on the PNG, by its seq:
    fractions of its width from the left and of its height from the top."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    features = geojson["features"]
    origin_at = next(
        (f["geometry"]["coordinates"][0] for f in features if f["properties"]["kind"] == "path"),
        None,
    ) or next((f["geometry"]["coordinates"] for f in features), [0.0, 0.0])
    origin = Position(origin_at[1], origin_at[0])

    def metres(coordinates: Sequence[Sequence[float]]) -> tuple[list[float], list[float]]:
        local = [north_east_m(origin, Position(lat, lon)) for lon, lat in coordinates]
        return [east for _, east in local], [north for north, _ in local]

    fig, ax = plt.subplots(figsize=(11, 5))
    for f in features:
        props, geometry = f["properties"], f["geometry"]
        if props["kind"] == "range":
            east, north = metres(geometry["coordinates"][0])
            ax.fill(east, north, color=props["fill"], alpha=0.08)
            ax.plot(east, north, color=props["stroke"], linewidth=0.8, linestyle="--")
        elif props["kind"] == "station":
            (x,), (y,) = metres([geometry["coordinates"]])
            ax.plot(x, y, marker="^", markersize=10, color=props["marker-color"])
            ax.annotate(
                f"station {props['controller']}",
                (x, y),
                textcoords="offset points",
                xytext=(6, 6),
                fontsize=8,
            )
    masters_drawn: set[int] = set()
    drones_named: set[str] = set()
    for f in features:
        props = f["properties"]
        if props["kind"] != "path":
            continue
        east, north = metres(f["geometry"]["coordinates"])
        label = None if props["master"] in masters_drawn else f"master {props['master']}"
        masters_drawn.add(props["master"])
        # A fleet's map: each drone's name where its path starts.
        if props.get("drone") is not None and props["drone"] not in drones_named:
            drones_named.add(props["drone"])
            ax.annotate(
                props["drone"],
                (east[0], north[0]),
                textcoords="offset points",
                xytext=(-4, -14),
                fontsize=9,
                fontweight="bold",
            )
        ax.plot(east, north, color=props["stroke"], linewidth=2.5, label=label)
    for f in features:
        props = f["properties"]
        if props["kind"] != "handover":
            continue
        (x,), (y,) = metres([f["geometry"]["coordinates"]])
        ax.plot(
            x,
            y,
            marker="*",
            markersize=14,
            color=props["marker-color"],
            markeredgecolor="black",
        )
        ax.annotate(
            f"{props['from']}→{props['to']} {props['delay_s']:.2f} s ({props['trigger']})",
            (x, y),
            textcoords="offset points",
            xytext=(0, -16),
            fontsize=8,
            ha="center",
        )
    places: dict[int, tuple[float, float]] = {}
    for f in features:
        props = f["properties"]
        if props["kind"] != "picture":
            continue
        (x,), (y,) = metres([f["geometry"]["coordinates"]])
        places[props["seq"]] = (x, y)
        ax.plot(x, y, marker="s", markersize=4, color=props["marker-color"], zorder=3)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(title)
    if masters_drawn:
        ax.legend(loc="upper left", fontsize=8)
    ax.grid(True, linewidth=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120, format="png")
    # Where the pictures ended up, now that drawing fixed the axes' limits and aspect.
    width, height = fig.canvas.get_width_height()
    on_picture = {}
    for seq, at in places.items():
        x, y = ax.transData.transform(at)
        on_picture[seq] = (float(x / width), float(1 - y / height))
    plt.close(fig)
    return on_picture
