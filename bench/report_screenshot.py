"""A picture of a `gdt report` page as headless Chromium draws it (the browser and flags of the browser test), for
the docs: `docs/report_test_scene.png` is the top of the paper test scene's report (its 3-D view) made with

    .venv/bin/gdt scene paper-test-scene workflows/data/paper_test_scene
    .venv/bin/gdt run workflows/test_scene.yaml --overwrite
    .venv/bin/gdt report out/test_scene_twin -o out/test_scene_report.html
    .venv/bin/python bench/report_screenshot.py out/test_scene_report.html docs/report_test_scene.png

Prints the seconds from opening the page to its 3-D view being drawn (``window.gdtReportReady``). Needs Debian's
chromium and chromium-driver (`make browser-deps`) and selenium (the `dev` extra).
"""

from __future__ import annotations

import argparse
import io
import time
from pathlib import Path

FLAGS = ("--headless=new", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox",
         "--disable-gpu-sandbox", "--hide-scrollbars")


def main() -> None:
    """Open the page, wait until it is drawn, save the top of it as PNG (under 1 MB)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("page", type=Path)
    ap.add_argument("png", type=Path)
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=1000)
    args = ap.parse_args()
    from PIL import Image
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.support.ui import WebDriverWait

    options = webdriver.ChromeOptions()
    options.binary_location = "/usr/bin/chromium"
    for flag in (*FLAGS, f"--window-size={args.width},{args.height}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=options)
    try:
        t0 = time.perf_counter()
        driver.get(args.page.resolve().as_uri())
        WebDriverWait(driver, 120).until(lambda d: d.execute_script("return window.gdtReportReady === true"))
        print(f"drawn in {time.perf_counter() - t0:.1f} s")
        driver.execute_async_script("const done = arguments[arguments.length - 1];"
                                    "requestAnimationFrame(() => requestAnimationFrame(() => done(true)));")
        image = Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB")
    finally:
        driver.quit()
    args.png.parent.mkdir(parents=True, exist_ok=True)
    image.save(args.png, optimize=True)
    if args.png.stat().st_size > 900_000:  # a busy page: a palette keeps the docs' picture under 1 MB
        image.quantize(colors=256, method=Image.Quantize.FASTOCTREE).save(args.png, optimize=True)
    print(f"wrote {args.png} ({args.png.stat().st_size / 1024:.0f} KB)")


if __name__ == "__main__":
    main()
