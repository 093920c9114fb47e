"""The viewer's first picture of a run, as a user who opens it sees it: the browser test's code
path (headless chromium, tests/apps/browser.py) on any run folder, e.g. the demo's.

    make demo
    .venv/bin/python benchmarks/viewer_screenshot.py outputs/demo/repair --out docs/viewer_demo.png

Prints the share of the canvas the map's colours cover (the browser test asks for over half, on
its own small run) once the picture has stopped changing.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests.apps.browser

from gsfix_online.apps.viewer import RunFolderSource, start_viewer  # noqa: E402
from tests.apps import browser  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="run folder of gsfix-online repair")
    ap.add_argument("--out", type=Path, required=True, help="PNG to write")
    ap.add_argument("--settle-s", type=float, default=120.0, help="longest wait for the picture")
    args = ap.parse_args()
    if (why := browser.missing()) is not None:
        print(f"viewer_screenshot: error: {why}", file=sys.stderr)
        return 2
    from PIL import Image

    viewer = start_viewer(RunFolderSource(args.run), port=0)
    try:
        with browser.chromium() as driver:
            driver.get(f"http://127.0.0.1:{viewer.server.get_port()}")
            browser.wait_for("the browser to connect", lambda: viewer.server.get_clients())
            # the picture once two canvases 2 s apart agree: every splat has arrived and drawn
            last, deadline = None, time.monotonic() + args.settle_s
            while time.monotonic() < deadline:
                browser.hide_notifications(driver)
                img = browser.canvas_image(driver)
                same = last is not None and img.shape == last.shape
                if (
                    same
                    and img.std() > 5
                    and np.abs(img.astype(int) - last.astype(int)).mean() < 0.5
                ):
                    break
                last = img
                time.sleep(2.0)
            else:
                print("viewer_screenshot: the picture kept changing; writing the last one")
            background = (img.astype(int) - 255).__abs__().sum(axis=2) < 30  # near-white
            print(f"map covers {1 - background.mean():.1%} of the canvas")
            args.out.parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(browser.screenshot(driver)).save(args.out)
            print(f"-> {args.out}")
    finally:
        viewer.server.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
