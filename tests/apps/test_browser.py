"""The viewer and the report page in a real browser: headless Debian chromium through selenium.

The viewer runs on a tiny run folder made here (a teal wall mesh, a red patch of splats in front
of it). The test checks that the scene draws and each layer's toggle hides it, measures two
known points on the wall with real clicks on the canvas, saves the named measurement and loads
it back through the GUI's buttons, and opens report.html from disk with every image loaded.

Clicks: the browser's camera is aimed (through viser's camera API) at each known point in turn,
with a narrow field of view, and the canvas is clicked at its centre; viser sends the click's
ray and the viewer's distance tool picks the point where it hits the mesh. Half a pixel of click
offset is 0.2 mm on the wall at that field of view.
"""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest

from gsfix_online.apps.viewer import RunFolderSource, set_client_pose, start_viewer
from gsfix_online.core.se3 import look_at
from tests.apps import browser
from tests.apps.test_viewer import (
    KNOWN_DISTANCE_M,
    POINT_A,
    POINT_B,
    SPLAT_RGB,
    WALL_RGB,
    make_run_folder,
)

pytestmark = pytest.mark.skipif(browser.missing() is not None, reason=str(browser.missing()))

AIM_FOV = math.radians(10.0)
AIM_DISTANCE_M = 1.0


def _aim(client, target: np.ndarray) -> None:
    """Point the browser's camera at ``target`` from AIM_DISTANCE_M in front of the wall and
    wait until the browser reports that pose back."""
    eye = target - np.array([0.0, 0.0, AIM_DISTANCE_M])
    set_client_pose(client, look_at(eye, target, (0, -1, 0)), AIM_FOV)
    browser.wait_for(
        "the browser camera to reach the aimed pose",
        lambda: (
            np.allclose(client.camera.position, eye, atol=1e-6)
            and np.allclose(client.camera.look_at, target, atol=1e-6)
            and abs(client.camera.fov - AIM_FOV) < 1e-6
        ),
    )
    time.sleep(0.3)  # one more frame drawn at that pose before the click


def test_viewer_draws_measures_and_keeps_labels_and_report_images_load(tmp_path):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    run = make_run_folder(tmp_path / "run")
    viewer = start_viewer(RunFolderSource(run), port=0)
    try:
        with browser.chromium() as driver:
            # 1. The scene draws: not uniform, the splats' red and the wall's blue on screen
            driver.get(f"http://127.0.0.1:{viewer.server.get_port()}")
            client = browser.wait_for(
                "the browser to connect", lambda: list(viewer.server.get_clients().values())
            )[0]
            browser.wait_for("its camera", lambda: client.camera._state.update_timestamp > 0)
            set_client_pose(client, look_at([0, 0, -0.5], [0, 0, 2.0], (0, -1, 0)), 1.0)

            def drawn():
                img = browser.screenshot(driver)
                red = browser.colour_pixels(img, SPLAT_RGB)
                wall = browser.hue_pixels(img, WALL_RGB)
                return (img, red, wall) if red > 2000 and wall > 2000 else None

            img, red, wall = browser.wait_for("the splats and the mesh to draw", drawn, 30.0)
            assert img.reshape(-1, 3).std(axis=0).max() > 20.0  # not uniform

            # Each layer's toggle hides it (a few hundred pixels of GUI and frusta share the hues)
            for layer, count in (
                ("Gaussian map", lambda im: browser.colour_pixels(im, SPLAT_RGB)),
                ("Mesh", lambda im: browser.hue_pixels(im, WALL_RGB)),
            ):
                browser.click_text(driver, layer)
                browser.wait_for(
                    f"the {layer} to hide", lambda c=count: c(browser.screenshot(driver)) < 500
                )
                browser.click_text(driver, layer)
                browser.wait_for(f"the {layer} to come back", lambda: drawn() is not None)

            # 2. The distance tool: switch it on in the GUI, click A then B on the canvas
            browser.click_text(driver, "Distance tool (click two points)")
            browser.wait_for("the tool to switch on", lambda: viewer.measure_box.value)
            for i, target in enumerate((POINT_A, POINT_B), start=1):
                _aim(client, target)
                ActionChains(driver).move_to_element(browser.canvas(driver)).click().perform()
                browser.wait_for(f"click {i} to pick", lambda i=i: len(viewer.points) == i)
                np.testing.assert_allclose(viewer.points[-1], target, atol=1e-3)
            assert viewer.distance_m == pytest.approx(KNOWN_DISTANCE_M, abs=1e-3)

            # 3. Name the measurement, save it, forget it, load it back: all through the GUI
            name_box = driver.find_element(
                By.XPATH, "//label[normalize-space(.)='Label name']/following::input[1]"
            )
            name_box.send_keys("wall span")
            browser.wait_for("the name to arrive", lambda: viewer.label_name.value == "wall span")
            browser.click_text(driver, "Save label")
            labels_file = run / "labels.json"
            browser.wait_for("labels.json", labels_file.is_file)
            saved = json.loads(labels_file.read_text())["labels"]
            assert [x["name"] for x in saved] == ["wall span"]
            assert saved[0]["distance_m"] == pytest.approx(KNOWN_DISTANCE_M, abs=1e-3)
            viewer.labels = []
            browser.click_text(driver, "Load labels")
            loaded = browser.wait_for("the labels to load", lambda: viewer.labels)
            assert [(x.name, round(x.distance_m, 6)) for x in loaded] == [
                ("wall span", saved[0]["distance_m"])
            ]

            # 4. The run's report, opened from disk: every image loaded
            driver.get((run / "report.html").as_uri())
            browser.wait_for(
                "the report's images",
                lambda: driver.execute_script(
                    "return Array.from(document.images).every(i => i.complete)"
                ),
            )
            widths = driver.execute_script(
                "return Array.from(document.images).map(i => i.naturalWidth)"
            )
            assert len(widths) >= 8 and all(w > 0 for w in widths), widths
    finally:
        viewer.server.stop()
