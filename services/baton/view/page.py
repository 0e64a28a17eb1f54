"""The live fleet view's page: one HTML document with its style and script inline,
which loads nothing from anywhere but its own server's ``/events`` (no tiles, no
fonts, no libraries: the server's Content-Security-Policy forbids the rest).

It draws each document the server sends (``state.fleet_view``) as it comes,
into an SVG in metres east and north of the first station: each station's
range as a circle in the station's colour (dashed when drained, grey when it
does not answer), each drone as a dot in its master's colour with its name,
master and state beside it and the trail it flew since the page opened, and
a table of the missions. Each drawn drone carries ``data-drone``,
``data-master``, ``data-state``, ``data-east`` and ``data-north``: what a
person sees, readable by a test.
"""

from __future__ import annotations

from baton.view.state import VIEW_FORMAT

PAGE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>baton fleet</title>
<style>
body { font: 14px/1.4 system-ui, sans-serif; margin: 0; color: #222; display: flex;
       flex-wrap: wrap; gap: 1em; padding: 1em; }
#map { flex: 3 1 640px; border: 1px solid #ccc; background: #fafafa; min-height: 480px; }
#side { flex: 1 1 320px; }
h1 { font-size: 1.3em; margin: 0 0 0.3em 0; }
table { border-collapse: collapse; width: 100%; }
th, td { border: 1px solid #ccc; padding: 0.15em 0.5em; text-align: left; }
th { background: #f3f3f3; }
.swatch { display: inline-block; width: 0.8em; height: 0.8em; border-radius: 50%;
          margin-right: 0.3em; vertical-align: middle; }
#live.ok { color: #2ca02c; } #live.lost { color: #d62728; }
ul#problems li { color: #a33; }
svg text { font-family: system-ui, sans-serif; paint-order: stroke; stroke: #fff; }
</style></head>
<body>
<svg id="map" xmlns="http://www.w3.org/2000/svg" preserveAspectRatio="xMidYMid meet">
  <g id="grid"></g><g id="ranges"></g><g id="trails"></g><g id="stations"></g>
  <g id="drones"></g>
</svg>
<div id="side">
  <h1>baton fleet</h1>
  <p><span id="live">connecting</span> <span id="updated"></span></p>
  <table id="missions"><thead><tr><th>drone</th><th>mission</th><th>master</th>
  <th>state</th><th>reqnr</th><th>ring</th></tr></thead><tbody></tbody></table>
  <h2 style="font-size:1.05em">Stations</h2>
  <table id="station-list"><thead><tr><th>station</th><th>range</th><th>missions</th>
  <th>state</th></tr></thead><tbody></tbody></table>
  <ul id="problems"></ul>
  <p style="color:#666;font-size:0.9em">Metres east and north of the first station.
  Drones are coloured by their master, trails since this page opened.</p>
</div>
<script>
"use strict";
const FORMAT = "FORMAT_NAME";
const NS = "http://www.w3.org/2000/svg";
const trails = new Map();
const TRAIL_POINTS = 2000;

function el(name, attrs, text) {
  const e = document.createElementNS(NS, name);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, String(v));
  if (text !== undefined) e.textContent = text;
  return e;
}
function cell(row, text, swatch) {
  const td = row.insertCell();
  if (swatch) {
    const s = document.createElement("span");
    s.className = "swatch";
    s.style.background = swatch;
    td.appendChild(s);
  }
  td.appendChild(document.createTextNode(text));
}
function clear(id) {
  const e = document.getElementById(id);
  while (e.firstChild) e.removeChild(e.firstChild);
  return e;
}

function draw(view) {
  if (view.format !== FORMAT) {
    document.getElementById("live").textContent = "unknown format " + view.format;
    return;
  }
  const [west, south, east, north] = view.bounds;
  const width = east - west, height = north - south;
  const map = document.getElementById("map");
  // North up: y is minus north.
  map.setAttribute("viewBox", `${west} ${-north} ${width} ${height}`);
  const unit = Math.max(width, height) / 400;  // one "pixel" of lines and dots
  const text = {"font-size": 5 * unit, "stroke-width": 1.2 * unit};

  const grid = clear("grid");
  const step = Math.pow(10, Math.floor(Math.log10(Math.max(width, height) / 2)));
  for (let x = Math.ceil(west / step) * step; x <= east; x += step)
    grid.appendChild(el("line", {x1: x, x2: x, y1: -north, y2: -south, stroke: "#e4e4e4",
                                 "stroke-width": unit / 2}));
  for (let y = Math.ceil(south / step) * step; y <= north; y += step)
    grid.appendChild(el("line", {x1: west, x2: east, y1: -y, y2: -y, stroke: "#e4e4e4",
                                 "stroke-width": unit / 2}));

  const ranges = clear("ranges"), stations = clear("stations");
  const stationRows = document.querySelector("#station-list tbody");
  while (stationRows.rows.length) stationRows.deleteRow(0);
  for (const s of view.stations) {
    const colour = s.answering ? s.colour : "#999999";
    ranges.appendChild(el("circle", {cx: s.east_m, cy: -s.north_m, r: s.range_m,
      fill: colour, "fill-opacity": 0.07, stroke: colour, "stroke-width": unit,
      "stroke-dasharray": s.drained ? `${4 * unit} ${3 * unit}` : "none"}));
    const g = el("g", {class: "station", "data-station": s.id,
                       "data-answering": s.answering});
    const r = 6 * unit;
    g.appendChild(el("path", {d: `M ${s.east_m} ${-s.north_m - r} l ${r} ${1.7 * r} ` +
                                 `l ${-2 * r} 0 z`, fill: colour}));
    g.appendChild(el("text", {x: s.east_m + 1.5 * r, y: -s.north_m - r, ...text},
                     `station ${s.id}` + (s.answering ? "" : " (silent)")));
    stations.appendChild(g);
    const row = stationRows.insertRow();
    cell(row, `${s.id} ${s.name}`, colour);
    cell(row, `${Math.round(s.range_m)} m`);
    cell(row, s.missions.join(", ") || "-");
    cell(row, !s.answering ? "silent" : s.drained ? "drained" : "in service");
  }

  const drones = clear("drones"), trailLayer = clear("trails");
  const rows = document.querySelector("#missions tbody");
  while (rows.rows.length) rows.deleteRow(0);
  for (const d of view.drones) {
    const master = d.master === null ? "?" : String(d.master);
    const row = rows.insertRow();
    row.dataset.drone = d.drone;
    cell(row, d.drone, d.colour);
    cell(row, String(d.mission));
    cell(row, master);
    cell(row, d.state + (d.answering ? "" : " (drone silent)"));
    cell(row, String(d.reqnr));
    cell(row, d.ring.join(","));
    if (d.place === null) continue;
    const key = `${d.mission}`;
    if (!trails.has(key)) trails.set(key, []);
    const trail = trails.get(key);
    const last = trail[trail.length - 1];
    if (!last || last[0] !== d.place.east_m || last[1] !== d.place.north_m)
      trail.push([d.place.east_m, d.place.north_m, d.colour]);
    if (trail.length > TRAIL_POINTS) trail.shift();
    for (let k = 1; k < trail.length; k++)
      trailLayer.appendChild(el("line", {x1: trail[k - 1][0], y1: -trail[k - 1][1],
        x2: trail[k][0], y2: -trail[k][1], stroke: trail[k][2], "stroke-width": 1.5 * unit}));
    const g = el("g", {class: "drone", "data-drone": d.drone, "data-mission": d.mission,
      "data-master": master, "data-state": d.state, "data-east": d.place.east_m,
      "data-north": d.place.north_m});
    g.appendChild(el("circle", {cx: d.place.east_m, cy: -d.place.north_m, r: 5 * unit,
      fill: d.colour, stroke: "#222", "stroke-width": unit / 2}));
    g.appendChild(el("text", {x: d.place.east_m + 7 * unit, y: -d.place.north_m + 14 * unit,
                              ...text},
      `${d.drone}: master ${master}, ${d.state}`));
    drones.appendChild(g);
  }
  const problems = clear("problems");
  for (const p of view.problems) {
    const li = document.createElement("li");
    li.textContent = p;
    problems.appendChild(li);
  }
  document.getElementById("updated").textContent =
    "as of " + new Date(view.at * 1000).toISOString().slice(11, 19) + " UTC";
}

const live = document.getElementById("live");
const events = new EventSource("events");
events.onopen = () => { live.textContent = "live"; live.className = "ok"; };
// The browser reconnects by itself; the page says so meanwhile.
events.onerror = () => { live.textContent = "reconnecting"; live.className = "lost"; };
events.onmessage = (message) => draw(JSON.parse(message.data));
</script>
</body></html>
""".replace("FORMAT_NAME", VIEW_FORMAT)
