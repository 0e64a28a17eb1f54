"""The fleet testbed's map and page (baton.testbed.fleet_report): stations once, each
flight's features tagged with its drone, the page self-contained."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from baton.config import BatonConfig
from baton.testbed.fleet_report import Flight, fleet_geojson, render_fleet_page
from baton.testbed.flight_map import TrackPoint

NETWORK = BatonConfig.model_validate(
    {
        "controllers": [
            {
                "id": sid,
                "address": f"127.0.0.1:{5000 + sid}",
                "location": {"latitude_deg": 47.3981912, "longitude_deg": longitude},
                "range_m": 500,
            }
            for sid, longitude in ((1, 8.545594), (2, 8.5522295))
        ],
        "tls": {"insecure": True},
    }
)
HANDOVER = {
    "from": 1,
    "to": 2,
    "after_reqnr": 9,
    "delay_s": 0.012,
    "trigger": "policy",
    "kind": "prepared",
    "reason": "nearest",
    "position": [47.3977, 8.549],
}


def flight(drone: str, longitudes: list[float], handovers: list[dict[str, Any]]) -> Flight:
    points = [
        TrackPoint(float(k), 47.397742, lon, 1 if k < 2 else 2) for k, lon in enumerate(longitudes)
    ]
    report = {"handovers": handovers}
    pictures = [{"effect": "picture", "seq": 1, "time": 0.0, "latitude_deg": 47.3977,
                 "longitude_deg": longitudes[0]}]  # fmt: skip
    return Flight(drone, report, points, pictures)


def test_the_stations_are_drawn_once_and_each_flight_is_named() -> None:
    flights = [
        flight("d1", [8.5456, 8.547, 8.549, 8.551], [HANDOVER]),
        flight("d2", [8.5522, 8.553], []),
    ]
    features = fleet_geojson(NETWORK, flights)["features"]
    kinds = [(f["properties"]["kind"], f["properties"].get("drone")) for f in features]
    assert kinds.count(("station", None)) == 2 and kinds.count(("range", None)) == 2
    assert kinds.count(("path", "d1")) == 2  # one a master
    assert ("handover", "d1") in kinds and ("picture", "d2") in kinds
    assert all(drone is not None for kind, drone in kinds if kind not in ("station", "range"))


def test_the_fleet_page_shows_every_mission_and_loads_nothing(tmp_path: Path) -> None:
    mission = {
        "drone": "d1",
        "mission_id": "1",
        "ring": [1, 2],
        "masters": [1, 2],
        "handovers": [HANDOVER],
        "exactly_once": True,
        "replicas_consistent": True,
        "failed": "",
        "ok": True,
    }
    failed = {**mission, "drone": "d<2>", "ok": False, "failed": "station 2: boom"}
    report = {
        "duration_s": 12.5,
        "speedup": 20,
        "stations": [{}, {}],
        "missions": [mission, failed],
        "summary": {"missions": 2, "ok": 1},
    }
    page = render_fleet_page(report, b"\x89PNG", tmp_path, {"JSON report": str(tmp_path / "r")})
    assert "default-src 'none'" in page and 'class="verdict fail">FAIL' in page
    assert page.count('<tr class="mission"') == 2 and "d&lt;2&gt;" in page
    assert "1 → 2" in page and "12 ms" in page and "station 2: boom" in page
    assert '<a href="r">JSON report</a>' in page
