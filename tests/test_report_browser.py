"""gdt report in a real browser: headless Chromium (Debian's chromium and chromium-driver, driven by selenium) opens
the page from a file:// URL with WebGL on SwiftShader (no GPU), and the test checks what a reader would see: no
console errors, nothing fetched, the 3-D view drawn in the new-change colour, and a click on a segment row framing
that segment (the view's picture and the plotly scene's axis ranges change). Skips, saying why, where Chromium, its
driver or selenium is missing (`make browser-deps` installs the first two) or the browser cannot start."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gdt_pipeline.report import write_report
from twin_store import STATE_COLORS

from .report_helpers import cube_twin

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
# new headless mode, WebGL through ANGLE on SwiftShader (the CPU renderer: CI machines have no GPU); no sandbox, as
# the tests run as root in a container
FLAGS = ("--headless=new", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox",
         "--disable-gpu-sandbox", "--window-size=1280,1000", "--hide-scrollbars")
NEW_RGB = np.round(STATE_COLORS[1] * 255)
TOLERANCE = 40  # per channel: markers are flat-coloured, their edges antialiased against the white background
MIN_NEW_PIXELS = 150  # the cube scene's new box is ~1000 points of 2 px markers
WAIT = 90  # seconds to wait for the page to draw (SwiftShader on a loaded 2-core machine); a wait, not a check


@pytest.fixture(scope="module")
def driver() -> Any:
    missing = [str(p) for p in (CHROMIUM, CHROMEDRIVER) if not p.exists()]
    if missing:
        pytest.skip(f"{' and '.join(missing)} missing: install Debian's chromium and chromium-driver "
                    f"(`make browser-deps`)")
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install -e '.[dev]')")
    from selenium.common.exceptions import WebDriverException
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in FLAGS:
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    try:
        drv = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
    except WebDriverException as exc:
        pytest.skip(f"headless Chromium cannot start: {str(exc.msg or exc).strip().splitlines()[0]}")
    drv.set_script_timeout(WAIT)
    yield drv
    drv.quit()


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory, registry) -> Path:
    root = tmp_path_factory.mktemp("browser")
    out = root / "report.html"
    write_report(cube_twin(root, registry), out)
    return out


def _open(driver: Any, page: Path) -> None:
    from selenium.webdriver.support.ui import WebDriverWait

    driver.get(page.resolve().as_uri())
    WebDriverWait(driver, WAIT).until(lambda d: d.execute_script("return window.gdtReportReady === true"))


def _frames(driver: Any, n: int = 3) -> None:
    """Let the browser draw ``n`` more animation frames (WebGL renders on them)."""
    driver.execute_async_script("const done = arguments[arguments.length - 1]; let left = arguments[0];"
                                "function tick() { if (--left <= 0) done(true); else requestAnimationFrame(tick); }"
                                "requestAnimationFrame(tick);", n)


def _view_pixels(driver: Any) -> np.ndarray:
    from PIL import Image

    view = driver.find_element("id", "view3d")
    driver.execute_script("arguments[0].scrollIntoView({block: 'center'});", view)  # all of it in the window
    png = view.screenshot_as_png
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int16)


def _new_pixels(img: np.ndarray) -> int:
    """Pixels of the new-change colour in the scene (right of the legend, whose swatches have it too)."""
    scene = img[:, img.shape[1] // 4:]
    return int(np.sum(np.max(np.abs(scene - NEW_RGB), axis=2) <= TOLERANCE))


def _scene(driver: Any) -> dict[str, Any]:
    return driver.execute_script("const s = document.getElementById('view3d').layout.scene;"
                                 "return {x: s.xaxis.range, y: s.yaxis.range, z: s.zaxis.range, camera: s.camera};")


def test_the_page_draws_offline_without_errors(driver: Any, report: Path) -> None:
    _open(driver, report)
    _frames(driver)
    severe = [e for e in driver.get_log("browser") if e.get("level") == "SEVERE"]
    assert not severe, severe
    fetched = driver.execute_script("return performance.getEntriesByType('resource').map(e => e.name);")
    assert not [u for u in fetched if u.startswith(("http:", "https:"))], fetched
    # WebGL really drew the scene: the new box's points are on the canvas in the new-change colour
    assert _new_pixels(_view_pixels(driver)) >= MIN_NEW_PIXELS
    # the "new" check box hides every new layer, and shows them again
    box = driver.find_element("css selector", 'input[data-toggle="state"][value="new"]')
    driver.execute_script("arguments[0].click();", box)
    _frames(driver)
    hidden = driver.execute_script("return document.getElementById('view3d').data"
                                   ".filter(t => t.meta && t.meta.state === 'new').map(t => t.visible);")
    assert hidden and not any(hidden)
    assert _new_pixels(_view_pixels(driver)) < MIN_NEW_PIXELS
    driver.execute_script("arguments[0].click();", box)
    _frames(driver)
    assert _new_pixels(_view_pixels(driver)) >= MIN_NEW_PIXELS


def test_clicking_a_segment_row_frames_it(driver: Any, report: Path) -> None:
    from selenium.webdriver.support.ui import WebDriverWait

    _open(driver, report)
    _frames(driver)
    before_img, before = _view_pixels(driver), _scene(driver)
    rows = driver.find_elements("css selector", "#segments tr[data-segment]")
    assert rows, "the cube twin has segments"
    sizes = [int(r.find_elements("tag name", "td")[3].text.replace(",", "")) for r in rows]
    row = rows[int(np.argmax(sizes))]  # the new box
    driver.execute_script("arguments[0].scrollIntoView({block: 'center'});", row)
    row.click()
    WebDriverWait(driver, WAIT).until(lambda d: _scene(d)["x"] != before["x"])
    _frames(driver)
    after_img, after = _view_pixels(driver), _scene(driver)
    assert (after["x"], after["y"], after["z"]) != (before["x"], before["y"], before["z"])
    assert after["x"][1] - after["x"][0] < before["x"][1] - before["x"][0]  # framed closer
    assert "selected" in row.get_attribute("class")
    assert driver.execute_script("const d = document.getElementById('view3d').data; return d[d.length - 1].visible;")
    assert before_img.shape == after_img.shape
    changed = np.mean(np.max(np.abs(after_img - before_img), axis=2) > 30)
    assert changed > 0.05, f"only {changed:.1%} of the view's pixels changed"
    assert _new_pixels(after_img) >= MIN_NEW_PIXELS  # the framed segment is the new box: larger now
    severe = [e for e in driver.get_log("browser") if e.get("level") == "SEVERE"]
    assert not severe, severe
