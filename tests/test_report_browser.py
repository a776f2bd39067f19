"""The report of the built-in demo, opened in a real headless Chromium (Selenium).

Skipped, with the reason, where Chromium, its driver or selenium is missing
(``scripts/test.sh`` installs them). Screenshots are kept as artefacts in the pytest
temporary folder; their paths are printed (``pytest -s`` or ``-rA`` shows them).
"""

from __future__ import annotations

import io
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from apo.cli import main
from apo.errors import ApoError

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def browser() -> Any:
    pytest.importorskip("selenium", reason="selenium not installed (extra 'browser')")
    from apo.report.browser import find_chromium, headless_chromium

    try:
        find_chromium()
    except ApoError as exc:
        pytest.skip(f"no browser: {exc}")
    with headless_chromium(1400, 1100) as drv:
        yield drv


@pytest.fixture(scope="module")
def demo_report(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("report-demo")
    assert main(["demo", "--out", str(out), "--no-plot"]) == 0
    assert (out / "report.html").is_file()
    return out / "report.html"


@pytest.fixture(scope="module")
def artefacts(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("report-screenshots")


def _pixels(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)


def _severe(drv: Any) -> list[str]:
    return [e["message"] for e in drv.get_log("browser") if e["level"] == "SEVERE"]


def _shot(drv: Any, name: str, artefacts: Path) -> Path:
    height = int(drv.execute_script("return document.body.scrollHeight"))
    drv.set_window_size(1400, max(1100, height))
    path = artefacts / name
    drv.save_screenshot(str(path))
    print(f"screenshot: {path}")
    return path


def test_demo_report_in_chromium(browser: Any, demo_report: Path, artefacts: Path) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    from apo.report.browser import open_report

    drv = browser
    ms = open_report(drv, demo_report)
    print(f"interactive after {ms:.0f} ms")
    assert _severe(drv) == [], "console errors on load"
    assert drv.find_element(By.ID, "errors").get_attribute("hidden") is not None
    _shot(drv, "report-frame0.png", artefacts)

    # the 3D canvas draws: many non-background pixels, several colours
    view = drv.find_element(By.ID, "view3d")
    px0 = _pixels(view.screenshot_as_png)
    drawn = np.any(np.abs(px0 - 255) > 12, axis=2)
    assert drawn.mean() > 0.05, f"3D view nearly blank ({drawn.mean():.3f} drawn)"
    assert len(np.unique(px0.reshape(-1, 3), axis=0)) > 50
    gl = drv.execute_script("return document.querySelectorAll('#view3d canvas').length")
    assert gl >= 1

    # the graph shows every state, and every transition's number
    task = drv.execute_script("return window.apo.data.task")
    ids = [s["id"] for s in task["states"]]
    texts = drv.execute_script(
        "return Array.from(document.querySelectorAll('#graph .annotation-text'))"
        ".map(function (e) { var l = e.querySelector('tspan.line');"
        " return (l || e).textContent; })"
    )
    firsts = {t.split(" ")[0].split("(")[0] for t in texts}
    assert set(ids) <= firsts, f"states missing in the graph: {set(ids) - firsts}"
    for k in range(1, len(task["transitions"]) + 1):
        assert any(t.startswith(f"({k})") for t in texts), f"transition {k} not labelled"
    if any(t["critical"] for t in task["transitions"]):
        assert any("CRITICAL" in t for t in texts)

    # the distinct-state view of the graph (task.json "graph") shows every contact state once
    from selenium.webdriver.support.ui import Select

    Select(drv.find_element(By.ID, "graph-mode")).select_by_value("distinct")
    time.sleep(0.5)
    texts = drv.execute_script(
        "return Array.from(document.querySelectorAll('#graph .annotation-text'))"
        ".map(function (e) { var l = e.querySelector('tspan.line');"
        " return (l || e).textContent; })"
    )
    distinct = {g["id"] for g in task["graph"]["states"]}
    assert distinct <= {t.split(" ")[0] for t in texts}
    Select(drv.find_element(By.ID, "graph-mode")).select_by_value("visits")

    # moving the slider (keyboard, as a user would) changes the state and its numbers
    state0 = drv.find_element(By.ID, "cur-state").text
    numbers0 = drv.find_element(By.ID, "cur-fig25").text
    slider = drv.find_element(By.ID, "slider")
    slider.send_keys(Keys.END)
    _wait_for(drv, lambda: drv.find_element(By.ID, "cur-state").text != state0)
    last = ids[-1]
    assert drv.find_element(By.ID, "cur-state").text == last
    assert drv.find_element(By.ID, "cur-fig25").text != numbers0
    assert drv.execute_script("return document.body.dataset.state") == last
    time.sleep(0.3)  # let the 3D view finish its redraw
    px1 = _pixels(view.screenshot_as_png)
    assert np.abs(px1 - px0).max(axis=2).astype(bool).mean() > 0.002, "3D view did not change"
    names = drv.execute_script("return document.getElementById('view3d').data.map(t => t.name)")
    assert "contact point" in names and any("normal" in n for n in names)
    # the timeline cursor follows the slider
    cursor = drv.execute_script(
        "var s = document.getElementById('timeline').layout.shapes; return s[s.length-1].x0"
    )
    assert cursor == pytest.approx(task["states"][-1]["times"][1], abs=1e-6)
    _shot(drv, "report-last-frame.png", artefacts)

    # one step back with the arrow key: one frame earlier
    slider.send_keys(Keys.ARROW_LEFT)
    _wait_for(drv, lambda: drv.execute_script("return document.body.dataset.frame") != "59")

    # a state with a singular element shows it marked
    sing = [i for i, s in enumerate(task["states"]) if s["singular"]]
    if sing:
        drv.execute_script(f"window.apo.seekState({sing[0]})")
        _wait_for(drv, lambda: drv.find_element(By.ID, "cur-state").text == ids[sing[0]])
        time.sleep(0.3)
        names = drv.execute_script("return document.getElementById('view3d').data.map(t => t.name)")
        assert "singular contact element" in names
        _shot(drv, "report-singular-state.png", artefacts)

    # clicking a row of the states table jumps there
    drv.find_element(By.CSS_SELECTOR, '#states-table tr[data-state="1"]').click()
    _wait_for(drv, lambda: drv.find_element(By.ID, "cur-state").text == ids[1])

    # play advances the frames
    drv.execute_script("window.apo.seek(0)")
    drv.find_element(By.ID, "play").click()
    _wait_for(drv, lambda: int(drv.execute_script("return document.body.dataset.frame")) > 3)
    drv.find_element(By.ID, "play").click()
    assert _severe(drv) == [], "console errors while interacting"


def _wait_for(drv: Any, cond: Any, timeout: float = 10.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return
        time.sleep(0.05)
    raise AssertionError("condition not met within the timeout")


def test_planned_motion_track_in_chromium(browser: Any, demo_report: Path, artefacts: Path) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import Select

    from apo.report.browser import open_report

    folder = demo_report.parent
    assert main(["plan", str(folder / "task.json"), "--out", str(folder / "plan")]) == 0
    html = folder / "report-motion.html"
    motion = str(folder / "plan" / "motion.json")
    assert main(["report", str(folder / "task.json"), "--motion", motion, "--out", str(html)]) == 0
    drv = browser
    open_report(drv, html)
    Select(drv.find_element(By.ID, "track")).select_by_visible_text("planned motion")
    slider = drv.find_element(By.ID, "slider")
    slider.send_keys(Keys.END)
    _wait_for(drv, lambda: "planned motion: sample" in drv.find_element(By.ID, "cur-frame").text)
    text = drv.find_element(By.ID, "cur-frame").text
    n = drv.execute_script("return window.apo.data.tracks[0].t.shape[0]")
    assert f"sample {n} of {n}" in text
    names = drv.execute_script("return document.getElementById('view3d').data.map(t => t.name)")
    assert "path: planned motion" in names and "grasped, planned motion" in names
    time.sleep(0.3)
    _shot(drv, "report-planned-motion.png", artefacts)
    assert _severe(drv) == []
