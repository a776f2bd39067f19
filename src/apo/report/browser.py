"""Open a report in a real headless browser (Debian's Chromium through Selenium).

Used by the browser tests and ``benchmarks/report.py``; also handy to check a report by
hand (``python -m apo.report.browser report.html shot.png``). Needs the ``selenium``
package (extra ``browser``) and a Chromium with its driver (Debian: ``apt-get install
chromium chromium-driver``; ``scripts/test.sh`` installs them when run as root).
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from apo.errors import ApoError

__all__ = ["CHROMIUM_FLAGS", "find_chromium", "headless_chromium", "open_report"]

CHROMIUM_FLAGS = (
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--enable-unsafe-swiftshader",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-dev-shm-usage",
)
"""Flags that make Chromium run headless as root in a container, WebGL in software."""


def find_chromium() -> tuple[str, str]:
    """Return ``(browser, driver)`` paths, or raise ApoError saying what is missing.

    ``APO_CHROMIUM`` and ``APO_CHROMEDRIVER`` override the search.
    """
    browser = os.environ.get("APO_CHROMIUM") or next(
        (p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if p),
        None,
    )
    driver = os.environ.get("APO_CHROMEDRIVER") or shutil.which("chromedriver")
    if not browser or not driver:
        missing = " and ".join(
            w for w, p in (("chromium", browser), ("chromedriver", driver)) if not p
        )
        raise ApoError(f"no {missing} found (Debian: apt-get install chromium chromium-driver)")
    return browser, driver


@contextmanager
def headless_chromium(width: int = 1400, height: int = 1000) -> Iterator[Any]:
    """Yield a Selenium Chrome driver on a headless Chromium with a fresh profile.

    The browser's console is captured (``driver.get_log("browser")``).
    """
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ModuleNotFoundError:
        raise ApoError("driving a browser needs selenium (pip install 'apo[browser]')") from None
    browser, driver_path = find_chromium()
    profile = tempfile.mkdtemp(prefix="apo-chromium-")
    opts = webdriver.ChromeOptions()
    opts.binary_location = browser
    for flag in (*CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}"):
        opts.add_argument(flag)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    drv = webdriver.Chrome(options=opts, service=Service(executable_path=driver_path))
    try:
        yield drv
    finally:
        drv.quit()
        shutil.rmtree(profile, ignore_errors=True)


def open_report(drv: Any, path: str | Path, *, timeout: float = 60.0) -> float:
    """Load a report and wait until it is drawn; return the time to interactive (ms).

    Time to interactive: from the start of navigation to the moment every plot is drawn
    and the controls respond (the page sets ``window.apoReady``).

    Raises
    ------
    ApoError
        If the page does not become ready within ``timeout`` seconds (its error box and
        console are in the message).
    """
    drv.get(Path(path).resolve().as_uri())
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        ready = drv.execute_script("return window.apoReady || null;")
        if ready is not None:
            return float(ready)
        time.sleep(0.05)
    errors = drv.execute_script(
        "var e = document.getElementById('errors'); return e ? e.textContent : '';"
    )
    raise ApoError(f"{path}: the report was not ready after {timeout:.0f} s: {errors}")


def main(argv: list[str] | None = None) -> int:
    """``python -m apo.report.browser REPORT.html SHOT.png``: screenshot of a report."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        sys.stderr.write("usage: python -m apo.report.browser REPORT.html SHOT.png\n")
        return 2
    with headless_chromium() as drv:
        ms = open_report(drv, args[0])
        drv.set_window_size(1400, int(drv.execute_script("return document.body.scrollHeight")))
        drv.save_screenshot(args[1])
        for entry in drv.get_log("browser"):
            sys.stderr.write(f"console {entry['level']}: {entry['message']}\n")
    sys.stdout.write(f"interactive after {ms:.0f} ms; screenshot {args[1]}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
