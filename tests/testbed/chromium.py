"""A page loaded in a real headless Chromium: Debian's (``deploy/install-chromium.sh``,
run by ``make test``), driven by playwright, which never downloads a browser here.

``render`` loads a local page with no network at all (any request that is not
the page itself is refused and recorded), and returns what a person would
meet: the console's errors and warnings, the page's uncaught errors, the
requests it tried, how many elements match each selector, whether every
image decoded, and a screenshot.

    python tests/testbed/chromium.py reports/testbed-report.html docs/report.png

takes the screenshot that docs/operating.md shows.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import pytest

CHROMIUM = "/usr/bin/chromium"
ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


@dataclass
class Rendered:
    """What the browser made of the page."""

    console: list[str] = field(default_factory=list)  # errors and warnings: "type: text"
    page_errors: list[str] = field(default_factory=list)
    requests: list[str] = field(default_factory=list)  # anything but the page and data: URIs
    counts: dict[str, int] = field(default_factory=dict)
    images_decoded: bool = False
    thumbnails_on_map: bool = False
    title: str = ""


def require_chromium() -> str:
    """Debian's chromium; skips the test where it is missing and cannot be installed
    (not root), fails where it should have been (root: ``make test`` installs it)."""
    found = shutil.which("chromium") or (CHROMIUM if os.path.exists(CHROMIUM) else None)
    if found is not None:
        return found
    if os.geteuid() != 0:
        pytest.skip(
            "no chromium, and only root installs it: sudo apt-get install chromium "
            "(deploy/install-chromium.sh)"
        )
    pytest.fail("no chromium: run deploy/install-chromium.sh (make test does, as root)")


def render(
    page: Path,
    selectors: Sequence[str],
    screenshot: Path | None = None,
    width: int = 1400,
    executable: str = CHROMIUM,
) -> Rendered:
    """Loads ``page`` (a local file) in headless Chromium, counts ``selectors``."""
    from playwright.sync_api import Route, sync_playwright

    url = page.absolute().as_uri()
    seen = Rendered()

    def route(request: Route) -> None:
        if request.request.url == url:
            request.continue_()
        else:
            seen.requests.append(request.request.url)
            request.abort()

    with tempfile.TemporaryDirectory(prefix="baton-chromium-") as profile, sync_playwright() as p:
        browser = p.chromium.launch_persistent_context(
            profile,
            executable_path=executable,
            headless=True,
            args=ARGS,
            viewport={"width": width, "height": 900},
            offline=True,
        )
        try:
            tab = browser.new_page()
            tab.on(
                "console",
                lambda m: (
                    seen.console.append(f"{m.type}: {m.text}")
                    if m.type in ("error", "warning")
                    else None
                ),
            )
            tab.on("pageerror", lambda e: seen.page_errors.append(str(e)))
            tab.route("**/*", route)
            tab.goto(url, wait_until="load", timeout=30_000)
            seen.title = tab.title()
            seen.counts = {s: tab.locator(s).count() for s in selectors}
            seen.images_decoded = tab.evaluate(
                "Array.from(document.images).every(i => i.complete && i.naturalWidth > 0)"
            )
            # Each thumbnail's centre lies on the map's picture.
            seen.thumbnails_on_map = tab.evaluate(
                """() => {
                    const map = document.getElementById('map-image');
                    if (!map) return false;
                    const m = map.getBoundingClientRect();
                    return Array.from(document.querySelectorAll('.thumb')).every(t => {
                        const r = t.getBoundingClientRect();
                        const x = r.left + r.width / 2, y = r.top + r.height / 2;
                        return x >= m.left && x <= m.right && y >= m.top && y <= m.bottom;
                    });
                }"""
            )
            if screenshot is not None:
                tab.screenshot(path=str(screenshot), full_page=True)
        finally:
            browser.close()
    return seen


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: python tests/testbed/chromium.py PAGE.html SCREENSHOT.png")
    shown = render(Path(sys.argv[1]), [".thumb", "tr.handover"], Path(sys.argv[2]))
    print(shown)
