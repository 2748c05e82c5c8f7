"""Headless Chromium driven by Selenium, shared by the tests that look at a page."""

from __future__ import annotations

import contextlib
import shutil
from collections.abc import Iterator

import pytest

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")

NEEDS_CHROMIUM = [
    pytest.mark.skipif(CHROMIUM is None, reason="chromium not on PATH (apt-get install chromium)"),
    pytest.mark.skipif(
        CHROMEDRIVER is None, reason="chromedriver not on PATH (apt-get install chromium-driver)"
    ),
]


@contextlib.contextmanager
def chromium(width: int = 1600, height: int = 1200) -> Iterator:
    """A headless Chromium WebDriver, quit on exit (skips the test without selenium)."""
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium not installed")
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                f"--window-size={width},{height}", "--hide-scrollbars"):  # fmt: skip
        opts.add_argument(arg)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)
    try:
        yield driver
    finally:
        driver.quit()


def needs_chromium(test):
    """Skip `test` (with the reason) where chromium or chromedriver is missing."""
    for mark in NEEDS_CHROMIUM:
        test = mark(test)
    return test
