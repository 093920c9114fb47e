"""Tests for gsfix_online/jobs/fixer_report.py: the report job end to end on a tiny ship tank."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gsfix_online.core.config import build
from gsfix_online.jobs.fixer_report import (
    CLASSICAL,
    VARIANTS,
    FixerReportConfig,
    baselines,
    run,
    summary,
)
from gsfix_online.repair.fallback import REGIONS
from gsfix_online.scene import ShipTankConfig, generate_ship_tank
from tests.fixer.conftest import TINY_DEFAULT


@pytest.fixture(scope="module")
def tiny_tank(tmp_path_factory):
    out = tmp_path_factory.mktemp("tank") / "scene"
    generate_ship_tank(ShipTankConfig(width=80, height=60, n_frames=12, n_novel=2, seed=3), out)
    return out


def _cfg(scene, out, *over):
    d = TINY_DEFAULT
    return build(
        FixerReportConfig,
        overrides=[
            f"scene={scene}",
            f"out={out}",
            "threads=1",
            "refine_iters=2",
            "finetune_steps=3",
            "ablation_steps=1",
            "fixer.model.random_init=true",
            f"fixer.model.default.codec_factor={d.codec_factor}",
            f"fixer.model.default.block_out_channels={list(d.block_out_channels)}",
            f"fixer.model.default.norm_num_groups={d.norm_num_groups}",
            "fixer.train.batch_size=1",
            "fixer.train.grad_accum=1",
            "fixer.train.pool_size=2",
            "fixer.inference.steps=2",
            *over,
        ],
    )


def test_report_rows_budgets_and_files(tiny_tank, tmp_path):
    rep = run(_cfg(tiny_tank, tmp_path / "r"))
    names = [r["method"] for r in rep["rows"]]
    assert names[:5] == ["raw_3dgs", "mesh_fill", "telea", "navier_stokes", "fsr"]
    assert len(names) == 5 + len(VARIANTS) == 11
    rows = {r["method"]: r for r in rep["rows"]}
    assert rows["gsfixer mesh+gs"]["steps"] == 3  # the headline row gets the full budget
    assert rows["gsfixer gs no masks"]["steps"] == 1 and rows["gsfixer mesh"]["steps"] == 1
    for r in rep["rows"]:
        assert len(r["psnr_db_per_view"]) == 2 and 0 < r["ssim"] <= 1
    assert rows["gsfixer mesh+gs"]["inference_s_per_view"] > 0
    assert set(rep["goals"]) >= {"above_mesh_fill", "inference_under_2_s_per_view"}
    best = max(CLASSICAL, key=lambda k: rows[k]["psnr_db"])
    assert rep["best_classical"] == best
    assert rep["goals"]["above_best_classical"] == (
        rows["gsfixer mesh+gs"]["psnr_db"] > rows[best]["psnr_db"]
    )
    # Per region class: view by view, and pooled (each pixel weighs the same)
    for r in rep["rows"]:
        assert len(r["regions_per_view"]) == 2 and set(r["regions"]) <= set(REGIONS)
        for reg, pooled in r["regions"].items():
            parts = [v[reg] for v in r["regions_per_view"] if reg in v]
            assert pooled["pixels"] == sum(p["pixels"] for p in parts) > 0
            assert pooled["ssim"] == pytest.approx(
                sum(p["ssim"] * p["pixels"] for p in parts) / pooled["pixels"]
            )
    assert sum(rows["raw_3dgs"]["regions"][k]["pixels"] for k in rows["raw_3dgs"]["regions"]) == (
        2 * 80 * 60
    )
    out = tmp_path / "r"
    assert json.loads((out / "fixer_report.json").read_text())["rows"] == json.loads(
        json.dumps(rep["rows"])
    )
    md = (out / "fixer_report.md").read_text()
    assert "| gsfixer mesh+gs no masks |" in md and md == summary(rep) + "\n"
    assert f"best classical baseline: {best}" in md and "| method | both dB | both SSIM |" in md
    html = (out / "fixer_report.html").read_text()
    assert "views/001_gsfixer_meshgs.png" in html and (out / "views/001_ground_truth.png").is_file()
    assert "per region class" in html and (out / "views/001_fsr.png").is_file()
    assert (out / "config.yaml").is_file()


def test_baselines_fill_holes_from_the_mesh():
    from gsfix_online.jobs.fixer_report import _View

    gt = np.full((4, 5, 3), 200, np.uint8)
    gs = gt.copy()
    gs[:, :2] = 0
    alpha = np.ones((4, 5), np.float32)
    alpha[:, :2] = 0
    mesh = np.full_like(gt, 190)
    valid = np.ones((4, 5), bool)
    valid[0, 0] = False
    out = baselines([_View("v", gt, gs, alpha, mesh, valid)])
    assert np.array_equal(out["raw_3dgs"][0], gs)
    assert (out["mesh_fill"][0][1:, :2] == 190).all() and (out["mesh_fill"][0][:, 2:] == 200).all()
    assert out["mesh_fill"][0][0, 0].tolist() == [0, 0, 0]  # neither covers it
    assert out["telea"][0][0, 0].min() > 150  # inpainted from its neighbours
    for row in ("navier_stokes", "fsr"):  # the other OpenCV inpaintings fill it too
        assert out[row][0][0, 0].min() > 150 and np.array_equal(
            out[row][0][1:], out["telea"][0][1:]
        )


def test_not_a_scene_folder(tmp_path):
    with pytest.raises(FileNotFoundError, match="not a ship-tank folder"):
        run(_cfg(tmp_path, tmp_path / "r"))
