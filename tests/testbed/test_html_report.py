"""The HTML report as a pure function of the report, the track and the pictures: what a
person sees is there, it holds everything it shows, and it says a failed run failed.

Rendered in a real Chromium by the end-to-end test of ``baton testbed``
(test_testbed.py); these need no browser.
"""

from __future__ import annotations

import re
import time
from pathlib import Path
from typing import Any

from baton.bench.timeline import timeline_rows
from baton.config import parse_config
from baton.drone.camera import generate_pixels, ppm_header, thumbnail_jpeg, thumbnail_name
from baton.sdk import Position, offset
from baton.testbed.flight_map import TrackPoint, flight_geojson
from baton.testbed.html_report import CSP, warnings, write_page
from baton.testbed.local import Snapshot
from baton.testbed.report import build_report
from baton.v1 import drone_pb2, ring_pb2

HOME = Position(47.397742, 8.545594)
PICTURE = ppm_header(64, 48) + generate_pixels(64, 48).tobytes()


def a_run(mission_error: str = "") -> tuple[Snapshot, Any]:
    """Three controllers, a scripted handover and a takeover, nine requests, three pictures."""
    config = parse_config(
        {"controllers": [{"id": i, "address": f"127.0.0.1:{7100 + i}"} for i in range(3)]}
    )
    drone = drone_pb2.DroneStatus()
    drone.handovers.add(
        old_master=0,
        new_master=1,
        after_reqnr=3,
        trigger=drone_pb2.HANDOVER_TRIGGER_SCRIPT,
        kind=drone_pb2.HANDOVER_KIND_COOPERATIVE,
        decided_at=1e9 + 3.5,
        delay_s=0.2,
    )
    drone.handovers.add(
        old_master=1,
        new_master=2,
        after_reqnr=6,
        trigger=drone_pb2.HANDOVER_TRIGGER_LOST,
        kind=drone_pb2.HANDOVER_KIND_TAKEOVER,
        decided_at=1e9 + 7.5,
        lost_at=1e9 + 6.5,
        delay_s=0.6,
    )
    for reqnr in range(1, 10):
        method = "TakePicture" if reqnr % 3 == 2 else "GetPosition"
        drone.audit.add(
            reqnr=reqnr,
            method=f"/baton.v1.{'Camera' if method == 'TakePicture' else 'Mobility'}/{method}",
            controller_id=(reqnr - 1) // 3,
            received_at=1e9 + reqnr,
            reply_bytes=len(PICTURE) if method == "TakePicture" else 40,
        )
    camera = []
    for k, east in enumerate((0.0, 60.0, 120.0), start=1):
        where = offset(HOME, 0.0, east)
        camera.append(
            {
                "seq": k,
                "time": 1e9 + 3 * k - 1,
                "effect": "picture",
                "resolution": "64x48",
                "bytes": len(PICTURE),
                "latitude_deg": where.latitude_deg,
                "longitude_deg": where.longitude_deg,
            }
        )
    run = Snapshot(drone, vehicle_effects=None, camera_effects=camera)
    for cid in range(3):
        run.controllers[cid] = ring_pb2.ControllerStatus(
            id=cid,
            mission=ring_pb2.MISSION_STATE_FAILED
            if mission_error and cid == 2
            else ring_pb2.MISSION_STATE_DONE,
        )
        if mission_error and cid == 2:
            run.controllers[cid].mission_error = mission_error
    return run, config


def write(tmp_path: Path, mission_error: str = "") -> tuple[str, dict[str, Any]]:
    run, config = a_run(mission_error)
    report = build_report(config, run, 3, 12.0, [(3, 1), (9, 0)], 60.0, grid_mission=False)
    tlog = tmp_path / "w" / "drone_2026.tlog"
    tlog.parent.mkdir()
    tlog.write_bytes(b"\0" * 1234)
    report["files"] = {"tlogs": [str(tlog)], "controller_logs": {"0": "/elsewhere/c0.sqlite"}}
    track = [
        TrackPoint(1e9 + t, *_lat_lon(offset(HOME, 0.0, 15.0 * t)), master)
        for t, master in enumerate([0, 0, 0, 0, 1, 1, 1, 2, 2])
    ]
    camera = run.camera_effects or []
    folder = tmp_path / "thumbnails"
    folder.mkdir()
    for picture in camera[:2]:  # the third: past the drone's limit, no thumbnail
        small = thumbnail_jpeg(PICTURE)
        assert small is not None
        (folder / thumbnail_name(picture["seq"])).write_bytes(small)
    page = tmp_path / "report.html"
    write_page(
        page,
        report,
        flight_geojson(config, report, track, camera),
        "a test run",
        timeline_rows(run, 0),
        0,
        camera,
        folder,
        map_path=tmp_path / "report.png",
        beside={"JSON report": str(tmp_path / "report.json")},
    )
    return page.read_text(encoding="utf-8"), report


def _lat_lon(p: Position) -> tuple[float, float]:
    return p.latitude_deg, p.longitude_deg


def test_the_page_shows_the_map_with_the_thumbnails_the_timeline_and_the_handovers(
    tmp_path: Path,
) -> None:
    started = time.monotonic()
    text, report = write(tmp_path)
    assert time.monotonic() - started < 10  # two matplotlib figures; about 1 s
    # Self-contained: every image inside the page, nothing loaded from anywhere.
    assert f'<meta http-equiv="Content-Security-Policy" content="{CSP}">' in text
    sources = re.findall(r'src="([^"]*)"', text)
    assert sources and all(s.startswith("data:image/") for s in sources), sources[:3]
    assert "<script" not in text and "<link" not in text
    assert 'id="map-image"' in text and 'id="timeline-image"' in text
    assert (tmp_path / "report.png").read_bytes()[:4] == b"\x89PNG"  # the map beside it
    # Two thumbnails, each placed on the map; the third picture kept none, and it says so.
    thumb = r'class="thumb" data-seq="(\d+)" style="left:([\d.]+)%;top:([\d.]+)%"'
    places = re.findall(thumb, text)
    assert [seq for seq, _, _ in places] == ["1", "2"]
    (_, x1, y1), (_, x2, y2) = places
    assert 0 < float(x1) < float(x2) < 100 and abs(float(y1) - float(y2)) < 1  # 60 m east
    assert "2 of the run&#x27;s 3 pictures as thumbnails" in text
    assert "1 without one" in text
    # The table: one row a handover, the takeover with its detection time.
    rows = re.findall(r'<tr class="handover">(.*?)</tr>', text)
    assert len(rows) == len(report["handovers"]) == 2
    assert "takeover (lost, detected after 1.000 s)" in rows[1]
    # The health: a planned handover missed fails the run, and says why.
    assert '<span class="verdict fail">FAIL</span>' in text
    assert "planned handover after request 9 to controller 0 did not happen" in text
    # Files: the .tlog beside the page by a relative link with its size; others by file://.
    assert 'class="tlog" href="w/drone_2026.tlog"' in text and "(1,234 bytes)" in text
    assert 'href="file:///elsewhere/c0.sqlite"' in text
    assert 'href="report.json"' in text
    # Its own size, exactly.
    stated = re.search(r"This page: ([\d,]+) bytes", text)
    assert stated is not None
    assert (
        int(stated.group(1).replace(",", ""))
        == len(text.encode())
        == ((tmp_path / "report.html").stat().st_size)
    )


def test_a_mission_error_is_a_warning_and_is_escaped(tmp_path: Path) -> None:
    text, _ = write(tmp_path, mission_error="<script>alert(1)</script> went wrong")
    assert "<script>" not in text
    assert "controller 2: mission failed: &lt;script&gt;alert(1)&lt;/script&gt; went wrong" in text
    assert '<span class="verdict fail">no</span>' in text  # not completed


def test_a_wait_that_needed_a_person_is_a_warning_and_an_expected_one_is_not() -> None:
    run, config = a_run()
    report = build_report(config, run, 3, 12.0, [(3, 1), (9, 0)], 60.0, grid_mission=False)
    report["waits"] = {
        "needs_person": [
            {
                "part": "c1",
                "key": "ring",
                "text": "ring stream to controller 2 down",
                "longest_s": 7.0,
                "first_s": 21.9,
            }
        ],
        "expected": [
            {
                "part": "c3",
                "key": "standby",
                "text": "out of range",
                "longest_s": 30.0,
                "first_s": 17.8,
            }
        ],
    }
    found = [w for w in warnings(report) if w.startswith("waited: ")]
    assert found == [
        "waited: c1: ring stream to controller 2 down (up to 7 s, first seen 22 s into the run)"
    ]
