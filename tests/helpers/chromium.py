"""A page loaded in a real headless Chromium: Debian's (``deploy/install-chromium.sh``,
run by ``make test``), driven by playwright, which never downloads a browser here.

``render`` loads a local page with no network at all (any request that is not
the page itself is refused and recorded), and returns what a person would
meet: the console's errors and warnings, the page's uncaught errors, the
requests it tried, how many elements match each selector, whether every
image decoded, and a screenshot. ``live_tab`` opens a page served over HTTP
(the live fleet view) for a test to watch as it changes, with the same
recording: requests to its own server pass, any other is refused and noted.

    python tests/helpers/chromium.py reports/testbed-report.html docs/report.png
    python tests/helpers/chromium.py http://127.0.0.1:8470/ docs/fleet-view.png 20

take the screenshots that docs/operating.md shows.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlsplit

import pytest

if TYPE_CHECKING:
    from playwright.sync_api import Page

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


@contextmanager
def _tab(
    allowed: Callable[[str], bool], seen: Rendered, width: int, executable: str, offline: bool
) -> Iterator[Page]:
    """A fresh headless Chromium's tab recording into ``seen`` its console's errors and
    warnings, its uncaught errors, and the requests ``allowed`` refuses (aborted);
    ``offline``: with no network at all (a local file)."""
    from playwright.sync_api import Route, sync_playwright

    def route(request: Route) -> None:
        if allowed(request.request.url):
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
            offline=offline,
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
            yield tab
        finally:
            browser.close()


def render(
    page: Path,
    selectors: Sequence[str],
    screenshot: Path | None = None,
    width: int = 1400,
    executable: str = CHROMIUM,
) -> Rendered:
    """Loads ``page`` (a local file) in headless Chromium, counts ``selectors``."""
    url = page.absolute().as_uri()
    seen = Rendered()
    with _tab(lambda u: u == url, seen, width, executable, offline=True) as tab:
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
    return seen


def _same_origin(url: str) -> Callable[[str], bool]:
    origin = urlsplit(url)[:2]
    return lambda u: urlsplit(u)[:2] == origin


@contextmanager
def live_tab(
    url: str, width: int = 1400, executable: str = CHROMIUM
) -> Iterator[tuple[Page, Rendered]]:
    """The page at ``url`` (http) loaded in headless Chromium, and what it has shown of
    errors and refused requests so far (anything not to ``url``'s own server)."""
    seen = Rendered()
    with _tab(_same_origin(url), seen, width, executable, offline=False) as tab:
        tab.goto(url, wait_until="load", timeout=30_000)
        seen.title = tab.title()
        yield tab, seen


if __name__ == "__main__":
    if len(sys.argv) not in (3, 4):
        sys.exit(
            "usage: python tests/helpers/chromium.py PAGE.html SCREENSHOT.png\n"
            "       python tests/helpers/chromium.py http://HOST:PORT/ SCREENSHOT.png [SECONDS]"
        )
    if sys.argv[1].startswith("http"):
        # A live page: the screenshot once a drone is drawn flying, SECONDS later (trails).
        with live_tab(sys.argv[1]) as (tab, seen):
            tab.wait_for_function(
                "() => document.querySelector('.drone[data-state=running]') !== null",
                timeout=300_000,
            )
            tab.wait_for_timeout(1000 * float(sys.argv[3] if len(sys.argv) == 4 else 0))
            tab.screenshot(path=sys.argv[2], full_page=True)
        print(seen)
    else:
        print(render(Path(sys.argv[1]), [".thumb", "tr.handover"], Path(sys.argv[2])))
