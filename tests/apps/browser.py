"""Headless Debian chromium through selenium, for the viewer and report tests.

WebGL runs in software (SwiftShader through ANGLE), so viser's canvas draws without a GPU. The
helpers poll with deadlines: a page that never draws fails with what was seen last.
"""

from __future__ import annotations

import io
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
WINDOW = (800, 600)
FLAGS = (
    "--headless=new",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--no-sandbox",
    "--disable-dev-shm-usage",
    f"--window-size={WINDOW[0]},{WINDOW[1]}",
)
T = TypeVar("T")


def missing() -> str | None:
    """Why the browser tests cannot run here, or None. Only a missing browser skips them: with
    chromium installed, a missing driver is a broken set-up and fails (make test-deps)."""
    if not CHROMIUM.exists():
        return f"{CHROMIUM} is missing (install chromium and chromium-driver: make test-deps)"
    return None


@contextmanager
def chromium() -> Iterator[Any]:
    """A headless chromium driven by selenium; quit on exit."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    assert CHROMEDRIVER.exists(), f"{CHROMEDRIVER} is missing: install chromium-driver"
    opts = webdriver.ChromeOptions()
    opts.binary_location = str(CHROMIUM)
    for flag in FLAGS:
        opts.add_argument(flag)
    driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=opts)
    try:
        yield driver
    finally:
        driver.quit()


def screenshot(driver: Any) -> npt.NDArray[np.uint8]:  # [H, W, 3] RGB
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB"))


def wait_for(
    what: str, fn: Callable[[], T | None], timeout_s: float = 15.0, every_s: float = 0.1
) -> T:
    """Poll ``fn`` until it returns something truthy; fail naming ``what`` after the deadline."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = fn()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(every_s)


def colour_pixels(
    img: npt.NDArray[np.uint8],  # [H, W, 3]
    rgb: tuple[int, int, int],
    tol: int = 40,
) -> int:
    """How many pixels are within ``tol`` of ``rgb`` in every channel."""
    diff = np.abs(img.astype(np.int16) - np.asarray(rgb, np.int16)).max(axis=2)
    return int((diff <= tol).sum())


def hue_pixels(
    img: npt.NDArray[np.uint8],  # [H, W, 3]
    rgb: tuple[int, int, int],
    min_cos: float = 0.99,
    min_level: int = 30,
) -> int:
    """How many pixels have the hue of ``rgb`` at any brightness (a lit surface is darker than
    its vertex colour): the cosine between the colour vectors is at least ``min_cos``."""
    x = img.reshape(-1, 3).astype(np.float64)
    ref = np.asarray(rgb, np.float64) / np.linalg.norm(rgb)
    norm = np.linalg.norm(x, axis=1)
    cos = (x @ ref) / np.maximum(norm, 1e-9)
    return int(((cos >= min_cos) & (x.max(axis=1) >= min_level)).sum())


def canvas(driver: Any) -> Any:
    """The largest <canvas> of the page (viser's 3D view)."""
    from selenium.webdriver.common.by import By

    canvases = driver.find_elements(By.TAG_NAME, "canvas")
    assert canvases, "the page has no canvas"
    return max(canvases, key=lambda c: c.size["width"] * c.size["height"])


def click_text(driver: Any, text: str) -> None:
    """Click the button or label of the GUI whose visible text is ``text``."""
    from selenium.webdriver.common.by import By

    xpath = f"//button[normalize-space(.)='{text}'] | //label[normalize-space(.)='{text}']"
    el = wait_for(f"a GUI element {text!r}", lambda: driver.find_elements(By.XPATH, xpath))[0]
    driver.execute_script("arguments[0].scrollIntoView({block: 'center'});", el)
    el.click()


def hide_notifications(driver: Any) -> None:
    """Remove viser's notifications from the page: in headless chromium it warns that WebGL runs
    in software, over a corner of the canvas (a user with a GPU never sees it)."""
    driver.execute_script(
        "document.querySelectorAll('.mantine-Notification-root').forEach(e => e.remove())"
    )


def canvas_image(driver: Any) -> npt.NDArray[np.uint8]:  # [h, w, 3] RGB
    """The screenshot's part that shows the 3D canvas (the GUI panel docks beside it)."""
    r = canvas(driver).rect
    img = screenshot(driver)
    y0, x0 = round(r["y"]), round(r["x"])
    return img[y0 : y0 + round(r["height"]), x0 : x0 + round(r["width"])]


def share(img: npt.NDArray[np.uint8], count: Callable[[npt.NDArray[np.uint8]], int]) -> float:
    """``count(img)`` as a share of the image's pixels."""
    return count(img) / float(img.shape[0] * img.shape[1])
