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

from gsfix_online.apps.viewer import (
    KEYFRAME_COLOR,
    OVERVIEW_FOV_Y,
    REPAIRED_COLOR,
    SKIPPED_COLOR,
    SYNTHESISED_TINT,
    TINT_SHARE,
    RunFolderSource,
    set_client_pose,
    start_viewer,
)
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


def _map_share(img: np.ndarray) -> float:
    """The share of the canvas in the map's colours: the wall's teal at any lighting, and the
    splats' red or the synthesised tint over their colour."""
    return browser.share(img, lambda im: browser.hue_pixels(im, WALL_RGB)
                         + browser.colour_pixels(im, SPLAT_RGB) + _tint_pixels(im))  # fmt: skip


def _tint_pixels(img: np.ndarray) -> int:
    tinted = TINT_SHARE * np.asarray(SYNTHESISED_TINT) + (1 - TINT_SHARE) * np.asarray(SPLAT_RGB)
    return browser.colour_pixels(img, tuple(int(c) for c in tinted), tol=30)


def _frusta_share(img: np.ndarray) -> float:
    """The share of the canvas in the frusta's colours (keyframes, repaired and skipped views)."""
    return browser.share(img, lambda im: browser.hue_pixels(im, KEYFRAME_COLOR)
                         + browser.hue_pixels(im, REPAIRED_COLOR)
                         + browser.colour_pixels(im, SKIPPED_COLOR, tol=12))  # fmt: skip


def test_viewer_opens_on_the_map_shows_cameras_on_demand_and_tints_what_was_synthesised(tmp_path):
    """The first picture, before any interaction, is the map: an overview that frames it, no
    camera frusta over it (they come with the Cameras toggle, small). The tint toggle marks the
    patch's Gaussians grown from a repaired view. GSFIX_VIEWER_SCREENSHOT=PATH keeps the first
    picture (docs/viewer.png is made so)."""
    import os

    from PIL import Image

    run = make_run_folder(tmp_path / "run")
    viewer = start_viewer(RunFolderSource(run), port=0)
    try:
        with browser.chromium() as driver:
            driver.get(f"http://127.0.0.1:{viewer.server.get_port()}")
            browser.wait_for("the browser to connect", lambda: viewer.server.get_clients())

            def wait_image(what, ok, timeout_s=15.0):  # the canvas once ok(canvas) holds
                def poll():
                    browser.hide_notifications(driver)
                    img = browser.canvas_image(driver)
                    return (img,) if ok(img) else None

                return browser.wait_for(what, poll, timeout_s)[0]

            # 1. The first picture, untouched: mostly map, no frusta
            first = wait_image("the map to fill the first picture", lambda im: _map_share(im) > 0.5,
                               30.0)  # fmt: skip
            map_share, frusta_share = _map_share(first), _frusta_share(first)
            assert map_share > 0.5 and frusta_share < 0.05, (map_share, frusta_share)
            if os.environ.get("GSFIX_VIEWER_SCREENSHOT"):
                Image.fromarray(browser.screenshot(driver)).save(
                    os.environ["GSFIX_VIEWER_SCREENSHOT"]
                )

            # 2. The cameras on demand, seen from behind them (the overview stands beside
            # them): the frusta appear, small beside the wall
            client = next(iter(viewer.server.get_clients().values()))
            set_client_pose(client, look_at([0.0, -0.6, -1.5], [0.0, 0.0, 1.0], (0, -1, 0)), 1.0)
            hidden = wait_image("the view from behind the cameras", lambda im: _map_share(im) > 0.2)
            assert _frusta_share(hidden) < 0.001
            browser.click_text(driver, "Cameras")
            shown = wait_image("the frusta to show", lambda im: _frusta_share(im) > 0.001)
            assert _frusta_share(shown) < 0.05
            browser.click_text(driver, "Cameras")
            wait_image("the frusta to go", lambda im: _frusta_share(im) < 0.001)
            set_client_pose(client, viewer.overview, OVERVIEW_FOV_Y)
            wait_image("the overview again", lambda im: _map_share(im) > 0.5)

            # 3. The synthesised tint: the patch's repaired part turns from red to the tint
            red = browser.colour_pixels(first, SPLAT_RGB)
            assert _tint_pixels(first) < 50
            browser.click_text(driver, "Tint synthesised")
            tinted = wait_image("the tint to show", lambda im: _tint_pixels(im) > 0.2 * red)
            assert browser.colour_pixels(tinted, SPLAT_RGB) < 0.8 * red
            assert np.abs(tinted.astype(int) - first.astype(int)).max(axis=2).mean() > 0.5
            browser.click_text(driver, "Tint synthesised")
            wait_image("the tint to go", lambda im: _tint_pixels(im) < 50)
    finally:
        viewer.server.stop()
