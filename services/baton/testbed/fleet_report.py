"""The fleet testbed's report: the whole fleet on one map (GeoJSON, PNG) and one HTML
page, from the single-mission report's own parts.

Each mission's report is ``report.build_report``'s, each flight's features are
``flight_map.flight_geojson``'s (its path by master, its handovers, its
pictures), tagged with the drone's name; the stations and their ranges are
drawn once, from the network. ``draw_flight`` draws the collection (naming
each drone where its path starts). ``render_fleet_page`` is pure: the fleet's
report and the map's PNG in, one self-contained page out (the single-mission
page's style and Content-Security-Policy: it loads nothing).
"""

from __future__ import annotations

import html
import io
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from baton.config import BatonConfig
from baton.testbed.flight_map import TrackPoint, draw_flight, flight_geojson
from baton.testbed.html_report import CSP, STYLE

FLEET_REPORT_FORMAT = "baton.testbed.fleet-report/1"
# What the fleet's features are, besides a flight's own.
NETWORK_KINDS = ("station", "range")


@dataclass(frozen=True)
class Flight:
    """One drone's mission as flown: its name, its report, its track and its pictures
    (the camera's effects lines)."""

    drone: str
    report: Mapping[str, Any]
    points: Sequence[TrackPoint]
    pictures: Sequence[Mapping[str, Any]] = ()


def fleet_geojson(network: BatonConfig, flights: Sequence[Flight]) -> dict[str, Any]:
    """Every station with its range once, then each flight's path, handovers and
    pictures with ``drone`` in their properties."""
    stations = flight_geojson(network, {"handovers": []}, [])["features"]
    features = [f for f in stations if f["properties"]["kind"] in NETWORK_KINDS]
    for flight in flights:
        own = flight_geojson(
            network, dict(flight.report), flight.points, [dict(p) for p in flight.pictures]
        )
        for f in own["features"]:
            if f["properties"]["kind"] in NETWORK_KINDS:
                continue
            f["properties"] = {"drone": flight.drone, **f["properties"]}
            features.append(f)
    return {"type": "FeatureCollection", "features": features}


def _e(value: object) -> str:
    return html.escape(str(value))


def _mission_row(mission: Mapping[str, Any]) -> str:
    ok = mission["ok"]
    masters = " → ".join(str(m) for m in mission["masters"]) or "-"
    delays = ", ".join(f"{h['delay_s'] * 1000:.0f} ms" for h in mission["handovers"]) or "-"
    cells = [
        (mission["drone"], "text"),
        (mission["mission_id"], ""),
        (",".join(map(str, mission["ring"])), "text"),
        (masters, "text"),
        (delays, "text"),
        ("yes" if mission["exactly_once"] else "NO", ""),
        ("consistent" if mission["replicas_consistent"] else "DIVERGED", ""),
        (mission["failed"] or ("pass" if ok else "FAIL"), "text"),
    ]
    tds = "".join(f'<td class="{cls}">{_e(text)}</td>' for text, cls in cells)
    return f'<tr class="mission" data-drone="{_e(mission["drone"])}">{tds}</tr>'


def render_fleet_page(
    report: Mapping[str, Any], map_png: bytes, page_dir: Path, beside: Mapping[str, str]
) -> str:
    """The fleet's page: the verdict, the map, a row a mission, the files beside it."""
    import base64
    import os

    missions = report["missions"]
    passed = report["summary"]["ok"] == len(missions)
    verdict = (
        f'<span class="verdict {"pass" if passed else "fail"}">{"PASS" if passed else "FAIL"}'
        "</span>"
    )
    header = "".join(
        f'<th class="text">{h}</th>'
        for h in (
            "drone",
            "mission",
            "ring",
            "masters",
            "handover delays",
            "exactly once",
            "replicas",
            "result",
        )
    )
    image = base64.b64encode(map_png).decode("ascii")
    files = "".join(
        f'<li><a href="{_e(os.path.relpath(path, page_dir))}">{_e(what)}</a></li>'
        for what, path in beside.items()
    )
    stations = len(report["stations"])
    title = f"Fleet: {len(missions)} drones over {stations} stations"
    body = (
        f"<h1>{_e(title)}</h1><p>{verdict} {report['summary']['ok']}/{len(missions)} missions "
        f"completed exactly once with consistent replicas in {report['duration_s']:.1f} s, "
        f"speed-up {report['speedup']:g}x.</p>"
        '<section id="map"><h2>The fleet on one map</h2>'
        f'<img class="figure" id="map-image" alt="the fleet map" '
        f'src="data:image/png;base64,{image}">'
        '<p class="small">Each path coloured by its master, named by its drone where it '
        "starts; stations and their ranges, each handover (★) with its delay.</p></section>"
        f'<section id="missions"><h2>Missions</h2><table><tr>{header}</tr>'
        f"{''.join(_mission_row(m) for m in missions)}</table></section>"
        f'<section id="files"><h2>Files</h2><ul>{files}</ul></section>'
    )
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f'<meta http-equiv="Content-Security-Policy" content="{CSP}">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>{_e(title)}</title><style>{STYLE}</style></head><body>{body}</body></html>\n"
    )


def write_fleet_report(
    report_path: Path, report: Mapping[str, Any], network: BatonConfig, flights: Sequence[Flight]
) -> tuple[Path, Path, Path]:
    """Writes the JSON report to ``report_path`` and, beside it, the map (``.geojson``,
    ``.png``) and the page (``.html``); returns those three paths."""
    report_path.parent.mkdir(parents=True, exist_ok=True)
    report_path.write_text(json.dumps(report, indent=2) + "\n")
    geojson = fleet_geojson(network, flights)
    map_path = report_path.with_suffix(".geojson")
    map_path.write_text(json.dumps(geojson) + "\n")
    drawn = io.BytesIO()
    draw_flight(geojson, drawn, f"Fleet: {len(flights)} drones")
    png_path = report_path.with_suffix(".png")
    png_path.write_bytes(drawn.getvalue())
    page = report_path.with_suffix(".html")
    beside = {"JSON report": str(report_path), "GeoJSON map": str(map_path)}
    page.write_text(
        render_fleet_page(report, drawn.getvalue(), page.parent, beside), encoding="utf-8"
    )
    return map_path, png_path, page
