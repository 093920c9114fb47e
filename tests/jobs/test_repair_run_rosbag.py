"""``gsfix-online repair`` on a ROS 2 bag at a processing resolution: one graph run as real
processes, which two tests read (a graph run costs about half a minute of both cores, and the
ROS 2 reader and the processing resolution are independent of each other). ``make test`` keeps a
module on one worker, so the run happens once."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from gsfix_online.core.config import read_yaml
from gsfix_online.jobs.repair_run import prepare, run_graph
from gsfix_online.sources.config import SourceConfig
from tests.jobs.test_repair_run import EAGER, FAST, _fixture, tank  # noqa: F401  (the fixture)


@pytest.fixture(scope="module")
def half_width_run(tank: Path, tmp_path_factory) -> dict[str, Any]:  # noqa: F811
    """The tank's 80x60 frames as a ROS 2 bag, run with ``source.max_width=40``,
    ``writer.upsample_to_camera`` and every 5th frame held out."""
    from gsfix_online.sources import open_source

    root = tmp_path_factory.mktemp("rosbag")
    src, extra = _fixture("ros2", root, list(open_source(SourceConfig(), tank / "tum")))
    out = root / "run"
    over = [*FAST, *EAGER, *extra, "source.max_width=40", "writer.upsample_to_camera=true"]
    graph, info, n = prepare(src, tank / "views3.txt", out, overrides=over, holdout=5)
    gt = sorted((out / "work" / "holdout" / "gt").glob("*.png"))  # written before the run
    log = io.StringIO()
    res = run_graph(graph, log=log, timeout_s=200)
    assert res.returncode == 0, res.message + log.getvalue()[-4000:]
    return {"out": out, "graph": graph, "info": info, "n": n, "gt": gt, "metrics": res.metrics}


def test_repair_runs_the_graph_on_a_ros2_bag(half_width_run: dict[str, Any]) -> None:
    info, out, m = half_width_run["info"], half_width_run["out"], half_width_run["metrics"]
    assert (info.format, info.frames, info.camera_size) == ("rosbag", 10, (80, 60))
    assert m is not None
    views = {v["view"]: v for v in m["views"]}
    assert {"000", "001", "002"} <= set(views)  # the 3 novel views, and the held-out frames
    for name, v in views.items():
        d = out / "views" / name
        assert (d / "gs.png").is_file() and (d / "final.png").is_file()
        assert (d / "fixed.png").is_file() == bool(v["repair"])
    # the view 100 m out of the tank is skipped, as from the MCAP log
    assert not views["002"]["repair"] and "little mapped surface" in views["002"]["reason"]
    assert any(v["repair"] for v in views.values())
    assert list((out / "map" / "point_cloud").glob("iteration_*/point_cloud.ply"))


def test_repair_at_a_processing_resolution_delivers_at_it_and_at_the_camera_size(
    half_width_run: dict[str, Any],
) -> None:
    """``source.max_width=40`` on the 80x60 tank: the maps, views, held-out ground truth and
    outputs are 40x32 (sides a multiple of 8: fx and fy scale apart); ``writer.
    upsample_to_camera`` adds output and final at 80x60."""
    info, out, m = half_width_run["info"], half_width_run["out"], half_width_run["metrics"]
    n, gt = half_width_run["n"], half_width_run["gt"]
    assert (info.width, info.height, info.camera_size, info.held_out, n) == (40, 32, (80, 60), 2, 5)
    wp = read_yaml(half_width_run["graph"])["nodes"]["writer"]["params"]
    assert (wp["camera_size"], wp["processing_size"]) == ([80, 60], [40, 32])
    assert len(gt) == 2 and all(cv2.imread(str(p)).shape == (32, 40, 3) for p in gt)
    assert m is not None and m["resolution"] == {"camera": [80, 60], "processing": [40, 32]}
    assert len(m["views"]) == 5
    for v in m["views"]:  # repaired or skipped, every view delivers an output
        d = out / "views" / v["view"]
        for name, shape in (
            ("gs", (32, 40)),
            ("output", (32, 40)),
            ("final", (32, 40)),
            ("output_camera", (60, 80)),
            ("final_camera", (60, 80)),
        ):
            assert cv2.imread(str(d / f"{name}.png")).shape[:2] == shape, (v["view"], name)
        # the camera-size file is the delivered repair, upsampled: area-resized back, it is
        # that repair up to the ringing of two resizes at its edges (measured: a mean of 0
        # to 1.1 levels a view, the worst pixel 31)
        up = cv2.imread(str(d / "output_camera.png"))
        back = cv2.resize(up, (40, 32), interpolation=cv2.INTER_AREA).astype(int)
        diff = np.abs(back - cv2.imread(str(d / "output.png")).astype(int))
        assert diff.mean() < 3.0, diff.mean()
    groups = m["summary"]["groups"]
    assert groups["holdout"]["final"]["views"] == 2
