"""The flight map as a pure function of the testbed file, the report and the track."""

from __future__ import annotations

from pathlib import Path

from baton.config import parse_config
from baton.sdk import Position, distance_m, offset
from baton.testbed.flight_map import (
    CIRCLE_VERTICES,
    TrackPoint,
    colour,
    draw_flight,
    flight_geojson,
)

HOME = Position(47.397742, 8.545594)


def test_stations_ranges_the_path_by_master_and_the_handovers(tmp_path: Path) -> None:
    stations = [offset(HOME, 50.0, east) for east in (0.0, 500.0)]
    config = parse_config(
        {
            "controllers": [
                {
                    "id": cid,
                    "address": f"127.0.0.1:{7100 + cid}",
                    "location": {"latitude_deg": p.latitude_deg, "longitude_deg": p.longitude_deg},
                    "range_m": 400,
                }
                for cid, p in enumerate(stations)
            ]
        }
    )
    track = []
    for t, (east, master) in enumerate([(0, 0), (100, 0), (200, 0), (300, 1), (400, 1)]):
        p = offset(HOME, 0.0, east)
        track.append(TrackPoint(float(t), p.latitude_deg, p.longitude_deg, master))
    at = offset(HOME, 0.0, 290.0)
    report = {
        "handovers": [
            # The policy's, with its position; then a scripted one, placed by time.
            {
                "from": 0,
                "to": 1,
                "after_reqnr": 9,
                "delay_s": 0.5,
                "trigger": "policy",
                "kind": "cooperative",
                "reason": "1 nearer",
                "position": [at.latitude_deg, at.longitude_deg],
                "decided_at": 2.4,
            },
            {
                "from": 1,
                "to": 0,
                "after_reqnr": 20,
                "delay_s": 0.4,
                "trigger": "script",
                "kind": "cooperative",
                "reason": "",
                "position": None,
                "decided_at": 3.9,
            },
        ]
    }
    collection = flight_geojson(config, report, track)
    kinds = [f["properties"]["kind"] for f in collection["features"]]
    assert kinds == ["station", "range", "station", "range", "path", "path", "handover", "handover"]
    circle = collection["features"][1]["geometry"]["coordinates"][0]
    assert len(circle) == CIRCLE_VERTICES + 1 and circle[0] == circle[-1]
    edge = Position(circle[5][1], circle[5][0])
    assert abs(distance_m(stations[0], edge) - 400.0) < 0.5
    first, second = collection["features"][4:6]
    assert first["properties"]["master"] == 0 and second["properties"]["master"] == 1
    assert first["properties"]["stroke"] == colour(0) != colour(1)
    # The second part starts where the first ended: the path has no gap.
    assert second["geometry"]["coordinates"][0] == first["geometry"]["coordinates"][-1]
    policy, scripted = collection["features"][6:]
    assert policy["geometry"]["coordinates"] == [
        round(at.longitude_deg, 7),
        round(at.latitude_deg, 7),
    ]
    assert policy["properties"]["reason"] == "1 nearer"
    nearest_in_time = track[4]  # decided at 3.9: the point of t = 4
    assert scripted["geometry"]["coordinates"] == [
        round(nearest_in_time.longitude_deg, 7),
        round(nearest_in_time.latitude_deg, 7),
    ]
    assert scripted["properties"]["reason"] == "script"
    picture = tmp_path / "map.png"
    draw_flight(collection, picture, "test")
    assert picture.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_pictures_on_the_map_and_where_they_are_on_its_png(tmp_path: Path) -> None:
    config = parse_config({"controllers": [{"id": 0, "address": "127.0.0.1:7100"}]})
    track = []
    for t, (north, east) in enumerate([(0, 0), (0, 100), (100, 100)]):
        at = offset(HOME, north, east)
        track.append(TrackPoint(float(t), at.latitude_deg, at.longitude_deg, 0))
    places = {1: (0.0, 0.0), 2: (0.0, 100.0), 3: (100.0, 100.0)}
    pictures: list[dict[str, object]] = [
        {"seq": 7, "time": 1.0, "effect": "picture"},  # taken where the position was unknown
    ]
    for seq, (north_m, east_m) in places.items():
        at = offset(HOME, north_m, east_m)
        pictures.append(
            {
                "seq": seq,
                "time": float(seq),
                "effect": "picture",
                "latitude_deg": at.latitude_deg,
                "longitude_deg": at.longitude_deg,
            }
        )
    collection = flight_geojson(config, {"handovers": []}, track, pictures)
    shown = [f for f in collection["features"] if f["properties"]["kind"] == "picture"]
    assert [f["properties"]["seq"] for f in shown] == [1, 2, 3]
    on_png = draw_flight(collection, tmp_path / "map.png", "pictures")
    assert set(on_png) == {1, 2, 3}
    (x1, y1), (x2, y2), (x3, y3) = (on_png[k] for k in (1, 2, 3))
    assert all(0 < v < 1 for v in (x1, y1, x2, y2, x3, y3))
    # East is right, north is up (the PNG's rows count from the top); equal scales.
    assert x2 > x1 and abs(y2 - y1) < 0.01 and y3 < y2 and abs(x3 - x2) < 0.01
    from PIL import Image

    with Image.open(tmp_path / "map.png") as image:
        width, height = image.size
        # Each picture's marker (#555555) is drawn where the fractions say.
        for x, y in on_png.values():
            assert image.convert("RGB").getpixel((round(x * width), round(y * height))) == (
                0x55,
                0x55,
                0x55,
            )
    assert abs((x2 - x1) * width - (y2 - y3) * height) < 2  # 100 m each way, in pixels
