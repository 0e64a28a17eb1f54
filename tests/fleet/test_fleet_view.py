"""``baton fleet view`` across real processes: a fleet testbed (2 drones, 3 stations,
each drone's corridor crossing a handover) watched in headless Chromium through the
view's page, as an operator opens it; and the testbed's fleet map and page at its end."""

from __future__ import annotations

import json
import signal
import subprocess
from pathlib import Path
from typing import Any

import yaml
from helpers.chromium import live_tab, render, require_chromium
from helpers.testbed_runs import baton_process
from playwright.sync_api import TimeoutError as PlaywrightTimeout
from waiting import until

from baton.testbed.fleet import NETWORK_FILE, REGISTRY_FILE

FLEET = Path(__file__).parents[2] / "examples" / "fleet.yaml"
# Each corridor 600 m from under its first station: past the midpoint to the next one,
# so that the nearest-station policy hands over once on the way; as short as that.
CORRIDOR_M = 600
# Slow enough that the view and the browser, started once the fleet's network file is
# written (its stations are up, its drones starting), see the drones before their
# handovers on a loaded machine.
SPEEDUP = 10
# The page notes each drone's master (consecutive repeats dropped) and where it was
# drawn, every time the drones are drawn again.
RECORDER = """() => {
    window.seen = {};
    const note = () => {
        for (const g of document.querySelectorAll('#drones .drone')) {
            const d = g.dataset.drone;
            const at = [Number(g.dataset.east), Number(g.dataset.north)];
            const s = window.seen[d] || (window.seen[d] = {masters: [], first: at, last: at});
            s.last = at;
            if (s.masters[s.masters.length - 1] !== g.dataset.master)
                s.masters.push(g.dataset.master);
        }
    };
    note();
    new MutationObserver(note).observe(document.getElementById('drones'), {childList: true});
}"""
# Every drone drawn, each moved 100 m or more, and a master change shown.
SHOWN = """(drones) => {
    const s = window.seen || {};
    return drones.every(d => s[d] && Math.hypot(s[d].last[0] - s[d].first[0],
                                                s[d].last[1] - s[d].first[1]) >= 100)
        && drones.some(d => s[d].masters.length >= 2);
}"""


def _contiguous(part: list[int], whole: list[int]) -> bool:
    return any(whole[k : k + len(part)] == part for k in range(len(whole) - len(part) + 1))


def test_the_live_view_shows_every_drone_moving_and_its_master_changing(tmp_path: Path) -> None:
    chromium = require_chromium()
    fleet = yaml.safe_load(FLEET.read_text())
    fleet["speedup"] = SPEEDUP
    for drone in fleet["drones"]:
        drone["mission"]["length_m"] = CORRIDOR_M
    fleet_file = tmp_path / "fleet.yaml"
    fleet_file.write_text(yaml.safe_dump(fleet))
    workdir = tmp_path / "w"
    testbed = baton_process(
        "testbed",
        "--fleet",
        str(fleet_file),
        "--workdir",
        str(workdir),
        "--report",
        str(tmp_path / "fleet.json"),
    )
    view: subprocess.Popen[str] | None = None
    try:
        network = workdir / NETWORK_FILE
        until(network.is_file, "the fleet's network file", 60)
        address_file = tmp_path / "view.address"
        view = baton_process(
            "fleet",
            "view",
            "--registry",
            str(workdir / REGISTRY_FILE),
            "--config",
            str(network),
            "--listen",
            "127.0.0.1:0",
            "--address-file",
            str(address_file),
        )
        until(address_file.is_file, "the view's address", 60)
        url = f"http://{address_file.read_text().split()[0]}/"
        with live_tab(url, executable=chromium) as (tab, shown):
            tab.evaluate(RECORDER)
            try:
                tab.wait_for_function(SHOWN, arg=["d1", "d2"], timeout=60_000)
            except PlaywrightTimeout:
                page = tab.evaluate("[window.seen, document.body.innerText]")
                raise AssertionError(f"not shown within 60 s: {page}, {shown}") from None
            seen: dict[str, Any] = tab.evaluate("window.seen")
            stations = tab.locator("#stations .station").count()
            live = tab.locator("#live").text_content()
            tab.screenshot(path=str(tmp_path / "fleet-view.png"))
        assert shown.console == [] and shown.page_errors == [] and shown.requests == [], shown
        assert stations == 3 and live == "live" and shown.title == "baton fleet"

        out, err = testbed.communicate(timeout=120)
        assert testbed.returncode == 0, out + err
        # Each drone's masters as the page showed them, in order, are a stretch of its
        # masters as the drone recorded them (its ring's first, then each handover's).
        rows = {line.split()[0]: line.split() for line in out.splitlines() if line}
        for drone, first in (("d1", 1), ("d2", 2)):
            handovers = [] if rows[drone][3] == "-" else rows[drone][3].split("->")
            recorded = [first, *map(int, handovers)]
            on_page = [int(m) for m in seen[drone]["masters"]]
            assert _contiguous(on_page, recorded), (drone, on_page, recorded)
        assert (tmp_path / "fleet-view.png").read_bytes()[:4] == b"\x89PNG"
        # At its end, the testbed drew the whole fleet on one map, and in its page.
        features = json.loads((tmp_path / "fleet.geojson").read_text())["features"]
        kinds = [(f["properties"]["kind"], f["properties"].get("drone")) for f in features]
        assert kinds.count(("station", None)) == 3 and kinds.count(("range", None)) == 3
        assert {("path", "d1"), ("path", "d2"), ("handover", "d1")} <= set(kinds)
        page = render(tmp_path / "fleet.html", ["#map-image", "tr.mission"], executable=chromium)
        assert page.console == [] and page.page_errors == [] and page.requests == [], page
        assert page.counts == {"#map-image": 1, "tr.mission": 2} and page.images_decoded
    finally:
        said = {}
        for name, process in (("view", view), ("testbed", testbed)):
            if process is not None and process.poll() is None:
                process.send_signal(signal.SIGINT)
                said[name] = process.communicate(timeout=30)
    # The view stops cleanly on Ctrl-C, its event stream open.
    assert view is not None and view.returncode == 0, said.get("view")
