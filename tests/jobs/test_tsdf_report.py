"""Report metrics on analytic inputs, and the CLI's report dispatch."""

from __future__ import annotations

import numpy as np
import pytest

from gsfix_online.apps.cli import REPORTS, build_parser
from gsfix_online.jobs.tsdf_report import image_metrics, nn_distances, surface_metrics


def test_surface_metrics_on_shifted_points():
    rng = np.random.default_rng(0)
    gt = rng.uniform(0, 1, (2000, 3))
    rec = gt[:1000] + [0.03, 0, 0]  # half the surface, 3 cm off
    d_rec, d_gt = nn_distances(rec, gt), nn_distances(gt, rec)
    assert np.all(d_rec <= 0.03 + 1e-12)
    m = surface_metrics(d_rec, d_gt, [0.02, 0.05])
    assert m["accuracy_cm"] <= 3.0 + 1e-9
    assert m["precision_5cm"] == 1.0 and m["fscore_5cm"] == pytest.approx(
        2 * m["recall_5cm"] / (1 + m["recall_5cm"])
    )


def test_image_metrics_psnr_and_depth_error():
    gt_c = np.full((10, 10, 3), 100, np.uint8)
    c = gt_c.copy()
    c[0, 0] = 110  # 50 pixels in both: mse = 3 * 100 / 150 = 2
    gt_d = np.ones((10, 10), np.float32)
    d = gt_d + 0.01
    d[:, 5:] = 0  # half not rendered
    m = image_metrics(c, d, gt_c, gt_d)
    assert m["coverage"] == 0.5 and m["depth_mae_cm"] == pytest.approx(1.0, abs=1e-4)
    assert m["psnr_db"] == pytest.approx(20 * np.log10(255) - 10 * np.log10(2))


def test_cli_report_dispatches_by_target():
    assert "tsdf" in REPORTS
    args = build_parser().parse_args(
        ["report", "tsdf", "tsdf.voxel_size=0.04", "--scene", "s", "--out", "o"]
    )
    assert args.target == "tsdf" and args.overrides == ["tsdf.voxel_size=0.04"]
