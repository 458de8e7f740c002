"""A real headless browser for the dashboard's tests: Debian's Chromium (``apt-get install
chromium``, as ``.ci/run`` does), driven by Playwright with its executable path, so nothing
downloads a browser. The flags keep Chromium off the network (it reaches for Google's hosts
at every start otherwise) and out of a sandbox it cannot have as root."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import pytest
from playwright.sync_api import Page, sync_playwright

from tests.conftest import MISSING_TOOL

CHROMIUM = Path("/usr/bin/chromium")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync"]

needs_chromium = pytest.mark.skipif(
    not CHROMIUM.exists(), reason=f"chromium is {MISSING_TOOL} (apt-get install chromium)")


@contextlib.contextmanager
def browser_page(url: str, *, width: int = 1400, height: int = 1000) -> Iterator[Page]:
    """A page open at ``url``; fails the test if the page raised or logged an error."""
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=str(CHROMIUM), args=FLAGS)
        try:
            page = browser.new_page(viewport={"width": width, "height": height})
            problems: list[str] = []
            page.on("pageerror", lambda error: problems.append(str(error)))
            page.on("console", lambda m: m.type == "error" and problems.append(m.text))
            page.goto(url)
            yield page
            assert problems == [], problems
        finally:
            browser.close()
