"""The testbed report as one self-contained HTML page, for a person to look at.

``render_page`` is pure: the report (``baton.testbed.report``), the flight map
and the timeline as PNG bytes, where on the map each picture was taken and
each picture's thumbnail in, one page out. Everything the page shows is inside
it (the images as ``data:`` URIs, the style inline, no script), and its
Content-Security-Policy forbids loading anything else, so it opens the same
with no network, mailed or archived. It links what it does not hold: the JSON
report and the GeoJSON map beside it, the drone's telemetry log (``.tlog``)
and the controllers' logs, and it says its own size.

``write_page`` draws the map (``flight_map.draw_flight``) and the Figure 5
timeline (``bench.timeline.draw_timeline``, the benchmark's own) and writes
the page, the map's PNG beside it.
"""

from __future__ import annotations

import base64
import html
import io
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from baton.drone.camera import thumbnail_name
from baton.testbed.faults import fault_lines
from baton.testbed.report import HANDOVER_COLUMNS, handover_cells, run_succeeded
from baton.testbed.waits import needed_a_person

# Content-Security-Policy: images from the page itself only, inline style, nothing else.
CSP = "default-src 'none'; img-src data:; style-src 'unsafe-inline'"
# On the map, a thumbnail is shown this wide (px); hovered, at its own size.
THUMBNAIL_ON_MAP_PX = 36

STYLE = """
body { font: 14px/1.45 system-ui, sans-serif; margin: 1.5em auto; max-width: 1400px;
       padding: 0 1em; color: #222; }
h1 { font-size: 1.5em; margin-bottom: 0.2em; } h2 { font-size: 1.15em; margin-top: 1.6em; }
.verdict { display: inline-block; padding: 0.15em 0.6em; border-radius: 4px; color: #fff;
           font-weight: bold; }
.pass { background: #2ca02c; } .fail { background: #d62728; } .none { background: #7f7f7f; }
table { border-collapse: collapse; margin: 0.5em 0; }
th, td { border: 1px solid #ccc; padding: 0.2em 0.6em; text-align: right; }
th { background: #f3f3f3; } td.text, th.text { text-align: left; }
.map { position: relative; display: inline-block; max-width: 100%; }
.map > img.figure, img.figure { max-width: 100%; height: auto; display: block; }
.thumb { position: absolute; transform: translate(-50%, -50%); line-height: 0;
         border: 1px solid #333; background: #fff; opacity: 0.75; }
.thumb img { width: THUMBpx; height: auto; }
.thumb:hover { z-index: 10; opacity: 1; } .thumb:hover img { width: auto; }
ul.warnings li { color: #a33; }
.small { color: #666; font-size: 0.9em; }
""".replace("THUMB", str(THUMBNAIL_ON_MAP_PX))


@dataclass
class PageParts:
    """What the page shows besides the report: the map and the timeline (PNG bytes,
    None where there is none), where each picture is on the map (fractions of its
    width from the left and of its height from the top, by the picture's seq), each
    picture's thumbnail (JPEG bytes, by seq) and the pictures the camera counted
    (its effects lines)."""

    map_png: bytes | None = None
    timeline_png: bytes | None = None
    places: Mapping[int, tuple[float, float]] = field(default_factory=dict)
    thumbnails: Mapping[int, bytes] = field(default_factory=dict)
    pictures: Sequence[Mapping[str, Any]] = ()


def _e(value: object) -> str:
    return html.escape(str(value))


def _data_uri(mime: str, data: bytes) -> str:
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


def _verdict(value: bool | None, yes: str = "yes", no: str = "no") -> str:
    if value is None:
        return '<span class="verdict none">not counted</span>'
    return f'<span class="verdict {"pass" if value else "fail"}">{yes if value else no}</span>'


def run_passed(report: Mapping[str, Any]) -> bool:
    """The testbed's verdict, as its exit code gives it: succeeded, no planned handover missed."""
    return run_succeeded(dict(report)) and not report["handovers_missed"]


def warnings(report: Mapping[str, Any]) -> list[str]:
    """What a person should look at: problems with the side effects, planned handovers
    that did not happen, controllers' mission errors, forced preparations, the vehicle's
    outages and refused MAVLink, the waits that needed a person, faults injected and
    parts that died."""
    found = [f"side effects: {p}" for p in report["side_effects"]["problems"]]
    found += [
        f"planned handover after request {reqnr} to controller {mid} did not happen"
        for reqnr, mid in report["handovers_missed"]
    ]
    found += [
        f"controller {c['id']}: mission {c['mission']}: {c['mission_error']}"
        for c in report["controllers"]
        if c["mission_error"]
    ]
    found += [
        f"handover {k} ({h['from']} to {h['to']}): its preparation timed out, "
        "the master moved anyway"
        for k, h in enumerate(report["handovers"], start=1)
        if h.get("prepare_timed_out")
    ]
    drone = report["drone"]
    if drone.get("vehicle_outages"):
        found.append(f"the vehicle's link was down {drone['vehicle_outages']} times")
    if drone.get("rejected"):
        found.append(f"the drone rejected {drone['rejected']} requests (not from the master)")
    refused = report["setup"]["vehicle"].get("refused_frames")
    if refused:
        found.append(f"the drone refused {refused} unsigned or badly signed MAVLink frames")
    if "waits" in report:  # the parts' stalls (baton.testbed.waits)
        found += [f"waited: {line}" for line in needed_a_person(report["waits"])]
    # The faults injected (--fault) and every part that died, with what the mission did.
    found += fault_lines(report)
    return found


def _link(target: str, page_dir: Path) -> str:
    """A link to a file from the page: relative when the file is under the page's folder,
    else its absolute file:// address."""
    path = Path(target).absolute()
    try:
        return path.relative_to(page_dir.absolute()).as_posix()
    except ValueError:
        return path.as_uri()


def _size(path: str) -> str:
    try:
        return f"{os.path.getsize(path):,} bytes"
    except OSError:
        return "missing"


def _health(report: Mapping[str, Any]) -> str:
    effects = report["side_effects"]
    rows = [
        ("mission completed", _verdict(report["completed"])),
        ("exactly once, by the drone's audit", _verdict(report["exactly_once"])),
        ("exactly once, by the side effects counted", _verdict(effects["exactly_once"])),
        ("replicas consistent", _verdict(report["replicas_consistent"])),
    ]
    table = "".join(f'<tr><td class="text">{_e(k)}</td><td>{v}</td></tr>' for k, v in rows)
    found = warnings(report)
    listed = (
        '<ul class="warnings">' + "".join(f"<li>{_e(w)}</li>" for w in found) + "</ul>"
        if found
        else "<p>No warnings.</p>"
    )
    camera = effects["pictures_taken"]
    commands = effects["vehicle_commands"]
    counted = (
        ", ".join(f"{name} {n}" for name, n in commands.items())
        if isinstance(commands, dict)
        else commands
    )
    drone = report["drone"]
    return (
        f'<section id="health"><h2>Health</h2><table class="verdicts">{table}</table>'
        f"<p>Counted where they happened: camera {_e(camera)} pictures "
        f"(expected {_e(effects['pictures_expected'])}); vehicle {_e(counted or 'nothing')}. "
        f"The drone executed {_e(drone['executed'])} requests, answered "
        f"{_e(drone['duplicates'])} repeats from its cache.</p>"
        f'<h3>Warnings</h3><div id="warnings">{listed}</div></section>'
    )


def _map(parts: PageParts) -> str:
    if parts.map_png is None:
        return '<section id="map"><h2>Flight</h2><p>No track was recorded.</p></section>'
    thumbs = []
    for picture in parts.pictures:
        seq = picture["seq"]
        where = parts.places.get(seq)
        small = parts.thumbnails.get(seq)
        if where is None or small is None:
            continue
        x, y = where
        title = (
            f"picture {seq} at {picture['latitude_deg']:.6f}, {picture['longitude_deg']:.6f}"
            f" ({picture.get('resolution', '?')}, {picture.get('bytes', 0):,} bytes)"
        )
        thumbs.append(
            f'<a class="thumb" data-seq="{seq}" style="left:{x * 100:.3f}%;top:{y * 100:.3f}%"'
            f' title="{_e(title)}"><img alt="{_e(title)}" src="{_data_uri("image/jpeg", small)}">'
            "</a>"
        )
    pictures = len(parts.pictures)
    note = f"{len(thumbs)} of the run's {pictures} pictures as thumbnails where they were taken"
    unplaced = pictures - len(thumbs)
    if unplaced:
        note += (
            f"; {unplaced} without one (no position known, or past the drone's "
            "limit of thumbnails kept)"
        )
    return (
        '<section id="map"><h2>Flight</h2><div class="map">'
        f'<img class="figure" id="map-image" alt="the flight map" '
        f'src="{_data_uri("image/png", parts.map_png)}">{"".join(thumbs)}</div>'
        f'<p class="small">Path coloured by master, stations and their range, each handover '
        f"with its delay (★); {_e(note)} (hover to enlarge).</p></section>"
    )


def _timeline(parts: PageParts) -> str:
    if parts.timeline_png is None:
        return ""
    return (
        '<section id="timeline"><h2>Timeline</h2>'
        f'<img class="figure" id="timeline-image" alt="the request timeline" '
        f'src="{_data_uri("image/png", parts.timeline_png)}">'
        '<p class="small">Inter-arrival time of the requests at the drone and the size of '
        "the master's log (computed by the flush rule from the drone's audit) over the "
        "request number; handovers dashed (the paper's Figure 5).</p></section>"
    )


def _handovers(report: Mapping[str, Any]) -> str:
    header = "".join(
        f'<th class="{"text" if c == "kind" else ""}">{_e(c)}</th>' for c in HANDOVER_COLUMNS
    )
    rows = []
    for k, h in enumerate(report["handovers"], start=1):
        *numbers, kind = handover_cells(k, h)
        cells = "".join(f"<td>{_e(c)}</td>" for c in numbers)
        reason = h.get("reason") or h["trigger"]
        rows.append(
            f'<tr class="handover">{cells}<td class="text">{_e(kind)}</td>'
            f'<td class="text">{_e(reason)}</td></tr>'
        )
    none = f'<tr><td class="text" colspan="{len(HANDOVER_COLUMNS) + 1}">none</td></tr>'
    body = "".join(rows) or none
    masters = " → ".join(str(m) for m in report["masters"])
    return (
        f'<section id="handovers"><h2>Handovers</h2><p>Masters: {_e(masters)}.</p>'
        f'<table id="handover-table"><thead><tr>{header}<th class="text">reason</th></tr>'
        f"</thead><tbody>{body}</tbody></table>"
        "<p class=\"small\">delay: from the drone's decision to the new master's first "
        "request; model: the paper's worst case T_log(0) + h·T_log(f + e) + T_conn.</p>"
        "</section>"
    )


def _controllers(report: Mapping[str, Any]) -> str:
    columns = ("controller", "state", "master", "reqnr", "lognr", "replayed", "invoked", "mission")
    header = "".join(f"<th>{c}</th>" for c in columns)
    rows = "".join(
        "<tr>"
        + "".join(
            f"<td>{_e(v)}</td>"
            for v in (
                c["id"],
                c["state"],
                "yes" if c["master"] else "no",
                c["reqnr"],
                c["lognr"],
                c["replayed"],
                c["invoked"],
                c["mission"],
            )
        )
        + "</tr>"
        for c in report["controllers"]
    )
    return (
        f'<section id="controllers"><h2>Controllers</h2><table><thead><tr>{header}</tr>'
        f"</thead><tbody>{rows}</tbody></table></section>"
    )


def _files(report: Mapping[str, Any], page_dir: Path, beside: Mapping[str, str]) -> str:
    items = [
        f'<li>{_e(what)}: <a href="{_e(_link(path, page_dir))}">{_e(Path(path).name)}</a></li>'
        for what, path in beside.items()
    ]
    files = report.get("files") or {}
    tlogs = files.get("tlogs") or []
    items += [
        f'<li>telemetry log (.tlog, MAVExplorer, mavlogdump.py): <a class="tlog" '
        f'href="{_e(_link(t, page_dir))}">{_e(t)}</a> ({_size(t)})</li>'
        for t in tlogs
    ]
    if not tlogs:
        items.append("<li>telemetry log (.tlog): none recorded</li>")
    items += [
        f'<li>controller {_e(cid)}\'s log (baton replay): <a href="{_e(_link(path, page_dir))}">'
        f"{_e(path)}</a></li>"
        for cid, path in (files.get("controller_logs") or {}).items()
    ]
    return f'<section id="files"><h2>Files</h2><ul>{"".join(items)}</ul></section>'


def render_page(
    report: Mapping[str, Any],
    parts: PageParts,
    title: str,
    page_dir: Path,
    beside: Mapping[str, str] | None = None,
) -> str:
    """The page, for a file in ``page_dir`` (links to files under it are relative);
    ``beside``: other files to link, by what they are. It states its own size."""
    passed = run_passed(report)
    mission = report["mission"]
    setup = report["setup"]
    head = (
        f"<h1>{_e(title)}</h1><p>{_verdict(passed, 'PASS', 'FAIL')} "
        f"mission {'completed' if report['completed'] else 'NOT completed'} in "
        f"{report['duration_s']:.1f} s: {mission['waypoints_visited']}/{mission['waypoints']} "
        f"waypoints, {mission['pictures']} pictures, {mission['invocations']} requests; "
        f"{setup['controllers']} controllers, flush limit {setup['flush_limit_bytes']:,} bytes, "
        f"speed-up {setup['speedup']:g}x, vehicle {_e(setup['vehicle']['autopilot'])}.</p>"
    )
    body = "".join(
        [
            head,
            _health(report),
            _map(parts),
            _timeline(parts),
            _handovers(report),
            _controllers(report),
            _files(report, page_dir, beside or {}),
        ]
    )

    def page(size: str) -> str:
        return (
            '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
            f'<meta http-equiv="Content-Security-Policy" content="{CSP}">'
            '<meta name="viewport" content="width=device-width, initial-scale=1">'
            f"<title>{_e(title)}</title><style>{STYLE}</style></head><body>{body}"
            f'<footer><p class="small" id="page-size">This page: {size}, self-contained '
            "(the images inside it; it loads nothing).</p></footer></body></html>\n"
        )

    # The page says its own size: the number's digits change the size, until they do not.
    text = page("0 bytes")
    for _ in range(5):
        size = f"{len(text.encode()):,} bytes"
        text = page(size)
        if len(text.encode()) == int(size.split()[0].replace(",", "")):
            break
    return text


def read_thumbnails(folder: Path | None, pictures: Sequence[Mapping[str, Any]]) -> dict[int, bytes]:
    """The thumbnails the drone's camera kept in ``folder``, by picture seq."""
    found: dict[int, bytes] = {}
    if folder is None:
        return found
    for picture in pictures:
        path = folder / thumbnail_name(picture["seq"])
        if path.is_file():
            found[picture["seq"]] = path.read_bytes()
    return found


def write_page(
    path: Path,
    report: Mapping[str, Any],
    geojson: Mapping[str, Any],
    title: str,
    timeline: Sequence[Mapping[str, Any]],
    flush_limit: int,
    pictures: Sequence[Mapping[str, Any]],
    thumbnails_dir: Path | None,
    map_path: Path | None = None,
    beside: Mapping[str, str] | None = None,
) -> None:
    """Draws the map (also written to ``map_path``) and the timeline (``timeline``: the
    run's ``bench.timeline.timeline_rows``) and writes the page to ``path``."""
    from baton.bench.timeline import draw_timeline
    from baton.testbed.flight_map import draw_flight

    pictures = [p for p in pictures if p.get("effect") == "picture"]
    parts = PageParts(pictures=pictures, thumbnails=read_thumbnails(thumbnails_dir, pictures))
    drawn = io.BytesIO()
    parts.places = draw_flight(dict(geojson), drawn, title)
    parts.map_png = drawn.getvalue()
    if map_path is not None:
        map_path.write_bytes(parts.map_png)
    if timeline:
        drawn = io.BytesIO()
        handovers = [h["after_reqnr"] for h in report["handovers"]]
        draw_timeline(timeline, handovers, flush_limit, drawn)
        parts.timeline_png = drawn.getvalue()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(render_page(report, parts, title, path.parent, beside), encoding="utf-8")
