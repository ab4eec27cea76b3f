"""Open a bake's report.html in a real headless Chromium (Debian's chromium and chromedriver, installed by
`make test`) and check what a reader sees: the verdict and the comparison on the first screen, every picture
decoded, and the before/after slider moving the split between EEVEE alone and EEVEE with the bake."""
from __future__ import annotations

import io
import shutil
from pathlib import Path

import numpy as np
import pytest

FIRST_SCREEN = (1280, 900)


def chromium_paths() -> tuple[str, str]:
    browser, driver = shutil.which("chromium") or shutil.which("chromium-browser"), shutil.which("chromedriver")
    if not (browser and driver):
        pytest.skip("needs Debian's chromium and chromium-driver; `make test` installs them")
    return browser, driver


def _pixels(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), np.float64)


def check_report_in_browser(report: Path, screenshot: Path) -> dict:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    browser, driver_path = chromium_paths()
    options = webdriver.ChromeOptions()
    options.binary_location = browser
    for argument in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                     "--force-device-scale-factor=1", f"--window-size={FIRST_SCREEN[0]},{FIRST_SCREEN[1]}"):
        options.add_argument(argument)
    driver = webdriver.Chrome(service=Service(driver_path), options=options)
    try:
        driver.get(Path(report).resolve().as_uri())
        decoded = driver.execute_async_script(
            "const done = arguments[arguments.length - 1];"
            "Promise.all([...document.images].map(i => i.decode().then(() => [i.alt, i.naturalWidth, i.naturalHeight],"
            " () => [i.alt, 0, 0]))).then(done);")
        assert decoded and all(width > 0 and height > 0 for _, width, height in decoded), decoded
        height = driver.execute_script("return window.innerHeight")
        verdict = driver.find_element(By.CSS_SELECTOR, "#verdict .verdict")
        slider = driver.find_element(By.CSS_SELECTOR, "figure.slider")
        assert verdict.rect["y"] < height and slider.rect["y"] < height, (verdict.rect, slider.rect, height)

        stack = slider.find_element(By.CSS_SELECTOR, ".stack")
        driver.execute_script("arguments[0].scrollIntoView()", slider)
        handle = slider.find_element(By.CSS_SELECTOR, "input[type=range]")
        handle.send_keys(Keys.HOME)  # the split at the left edge: all of the picture is EEVEE with the bake
        after = _pixels(stack.screenshot_as_png)
        handle.send_keys(Keys.END)  # at the right edge: all of it is the image compared with (EEVEE alone)
        before = _pixels(stack.screenshot_as_png)
        driver.execute_script("arguments[0].value = 50; arguments[0].dispatchEvent(new Event('input'))", handle)
        half = _pixels(stack.screenshot_as_png)
        width = half.shape[1]
        left, right = slice(0, width // 2 - 3), slice(width // 2 + 3, width)
        assert np.abs(before - after).mean() > 0.5, "EEVEE alone and with the bake look the same"
        # at 50 the left half is EEVEE alone and the right half EEVEE with the bake
        assert np.abs(half[:, left] - before[:, left]).mean() < 0.5 * np.abs(before[:, left] - after[:, left]).mean()
        assert np.abs(half[:, right] - after[:, right]).mean() < 0.5 * np.abs(before[:, right] - after[:, right]).mean()

        driver.execute_script("window.scrollTo(0, 0)")
        driver.save_screenshot(str(screenshot))  # the first screen, as a reader opens the page
        page = _pixels(Path(screenshot).read_bytes())
        assert page.std() > 10, "the page screenshot is blank"
        return {"images": len(decoded), "screenshot": str(screenshot)}
    finally:
        driver.quit()
