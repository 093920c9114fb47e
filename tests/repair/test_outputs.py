"""The repair output folder: files as views arrive, metrics.json content, the report page."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from gsfix_online.core.metrics import psnr, ssim, ssim_map
from gsfix_online.repair.baselines import inpaint, inpaint_telea, mesh_fill
from gsfix_online.repair.fallback import REGIONS, ref_inpaint, regions
from gsfix_online.repair.outputs import CLASSICAL, STAGES, RepairOutputs

H, W = 24, 32


def img(value: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(value + rng.integers(-20, 21, (H, W, 3)), 0, 255).astype(np.uint8)


CAM = {"K": [30.0, 0, 15.5, 0, 30.0, 11.5, 0, 0, 1], "T_world_cam": np.eye(4).ravel().tolist(),
       "width": W, "height": H}  # fmt: skip
REF_VALID = np.zeros((H, W), bool)
REF_VALID[:12, 4:20] = True  # what the real frames nearest the views see: across both holes
REF = np.where(REF_VALID[..., None], img(105, seed=7), 0).astype(np.uint8)  # their warp
SCORE = {"surface_fraction": 1.0, "hole_fraction": 0.25, "disagree_fraction": 0.0,
         "underobserved_fraction": math.nan}  # fmt: skip


@pytest.fixture
def run(tmp_path):
    gt_dir = tmp_path / "gt"
    gt_dir.mkdir()
    gt = {i: img(100 + 20 * i, seed=i) for i in range(2)}
    for i, g in gt.items():
        cv2.imwrite(str(gt_dir / f"{i:03d}.png"), cv2.cvtColor(g, cv2.COLOR_RGB2BGR))
    out = RepairOutputs(tmp_path / "out", gt_dir)
    alpha = np.ones((H, W), np.float32)
    alpha[:, :8] = 0.0
    valid = np.ones((H, W), bool)
    valid[:4] = False
    # view 0: repaired; view 1: skipped
    out.on_decision(0, True, "holes 25.0% > 2.0%", SCORE, CAM, seconds=0.5)
    out.on_renders(0, gs=img(90), alpha=alpha, mesh=img(110), valid=valid)
    out.on_ref(0, REF, REF_VALID)
    out.on_fixed(0, img(100, seed=5), {"fix_s": 0.2, "render_s": 0.1}, {"version": 2, "step": 40})
    out.on_distilled(0, 1.5)
    out.on_decision(1, False, "map explains the view (holes 0.0%, disagreement 0.0%)", SCORE, CAM)
    out.on_ref(1, REF, REF_VALID)  # before its renders: ref_inpaint waits for the mesh render
    out.on_renders(1, gs=img(120), alpha=np.ones((H, W), np.float32), mesh=img(120), valid=valid)
    for i in range(2):
        out.on_final(i, gt[i])
    return out, gt, alpha, valid, tmp_path / "out"


def test_files_follow_the_layout(run):
    out, _, alpha, valid, d = run
    assert sorted(p.name for p in (d / "views" / "000").iterdir()) == [
        "alpha.png", "final.png", "fixed.png", "gs.png", "gs_inpaint.png", "inpaint.png",
        "inpaint_ns.png", "mesh.png", "mesh_fill.png", "mesh_inpaint.png", "output.png",
        "ref_inpaint.png", "ref_warp.png",
    ]  # fmt: skip
    assert sorted(p.name for p in (d / "views" / "001").iterdir()) == [
        "alpha.png", "final.png", "gs.png", "gs_inpaint.png", "inpaint.png", "inpaint_ns.png",
        "mesh.png", "mesh_fill.png", "mesh_inpaint.png", "ref_inpaint.png", "ref_warp.png",
    ]  # fmt: skip
    # FSR (seconds per real view): the writer makes it one view at a time while it waits
    assert out.finish_baselines(limit=1) == 1
    made = sorted(p.parent.name for p in (d / "views").glob("*/inpaint_fsr.png"))
    assert len(made) == 1
    assert out.finish_baselines() == 1  # the other one, with the metrics
    assert out.finish_baselines() == 0  # each once
    assert (d / "views" / "000" / "inpaint_fsr.png").is_file()
    v0 = d / "views" / "000"
    back = cv2.cvtColor(cv2.imread(str(v0 / "gs.png")), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(back, img(90))  # PNG: lossless, RGB order kept
    a8 = cv2.imread(str(v0 / "alpha.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(a8, np.where(alpha > 0, 255, 0).astype(np.uint8))
    fill = mesh_fill(img(90), alpha, img(110), valid)
    for name, want in (
        ("mesh_fill", fill.image),
        ("inpaint", inpaint_telea(fill.image, fill.missing)),
        ("inpaint_ns", inpaint(fill.image, fill.missing, "ns")),
        ("inpaint_fsr", inpaint(fill.image, fill.missing, "fsr")),
        ("mesh_inpaint", inpaint_telea(img(110), ~valid)),
        ("gs_inpaint", inpaint_telea(img(90), alpha < 0.5)),
        ("ref_warp", REF),
        ("ref_inpaint", ref_inpaint(img(110), valid, REF, REF_VALID, img(90), alpha)),
    ):
        got = cv2.cvtColor(cv2.imread(str(v0 / f"{name}.png")), cv2.COLOR_BGR2RGB)
        np.testing.assert_array_equal(got, want)


def test_metrics_json_holds_decisions_timings_and_every_stage(run):
    out, gt, alpha, valid, d = run
    m = out.write({"timings_s": {"collect_s": 3.0}, "map": "map", "mesh": "mesh.ply"})
    assert json.loads((d / "metrics.json").read_text()) == m
    s = m["summary"]
    assert (s["views"], s["repaired"], s["skipped"]) == (2, 1, 1)
    assert s["skip_reasons"] == {"map explains the view": 1}
    v0, v1 = m["views"]
    assert v0["repair"] and not v0["skipped"] and v1["skipped"] and v1["reason"].startswith("map")
    assert v0["score"]["underobserved_fraction"] is None  # NaN is written as null
    fsr_s = v0["timings_s"].pop("inpaint_fsr_s")
    assert 0 < fsr_s < 5 and s["stage_time_totals_s"]["inpaint_fsr_s"] >= fsr_s
    assert v0["timings_s"] == {"score_s": 0.5, "fix_s": 0.2, "render_s": 0.1, "distill_s": 1.5}
    assert v0["model"] == {"version": 2, "step": 40}
    assert set(v0["files"]) == {
        "gs", "alpha", "gs_inpaint", "mesh", "mesh_fill", "inpaint", "inpaint_ns", "inpaint_fsr",
        "mesh_inpaint", "ref_warp", "ref_inpaint", "fixed", "output", "final", "provenance",
    }  # fmt: skip
    assert "fixed" not in v1["files"] and "inpaint" in v1["files"]
    # Each stage's figures are the metrics of that image against the ground truth
    fill = mesh_fill(img(90), alpha, img(110), valid)
    want = {
        "gs": img(90), "mesh": img(110), "fixed": img(100, seed=5), "final": gt[0],
        "mesh_fill": fill.image, "inpaint": inpaint_telea(fill.image, fill.missing),
        "fixed_or_gs": img(100, seed=5), "output": img(100, seed=5),
        "mesh_inpaint": inpaint_telea(img(110), ~valid),
        "gs_inpaint": inpaint_telea(img(90), alpha < 0.5),
        "inpaint_ns": inpaint(fill.image, fill.missing, "ns"),
        "inpaint_fsr": inpaint(fill.image, fill.missing, "fsr"),
        "ref_warp": REF, "ref_inpaint": ref_inpaint(img(110), valid, REF, REF_VALID, img(90), alpha),
    }  # fmt: skip
    assert set(want) | {"output_or_gs"} == set(STAGES) == set(v0["metrics"])
    for stage, im in want.items():
        got = v0["metrics"][stage]
        if stage == "final":
            assert got["psnr_db"] is None and got["ssim"] == pytest.approx(1.0)  # identical: inf
            continue
        assert got["psnr_db"] == pytest.approx(psnr(im, gt[0]), abs=1e-5)
        assert got["ssim"] == pytest.approx(ssim(im, gt[0]), abs=1e-6)
    assert "fixed" not in v1["metrics"] and v1["metrics"]["fixed_or_gs"] == v1["metrics"]["gs"]
    assert s["stages"]["fixed"]["views"] == 1 and s["stages"]["gs"]["views"] == 2
    assert s["stages"]["gs"]["psnr_db"] == pytest.approx(
        np.mean([v0["metrics"]["gs"]["psnr_db"], v1["metrics"]["gs"]["psnr_db"]])
    )
    assert s["stage_time_totals_s"]["fix_s"] == pytest.approx(0.2)
    assert m["timings_s"] == {"collect_s": 3.0} and m["map"] == "map"
    page = (d / "report.html").read_text()
    assert "views/000/fixed.png" in page and "views/001/fixed.png" not in page
    assert "views/000/inpaint.png" in page and "views/000/inpaint_fsr.png" in page
    # The best classical baseline is named: the one of CLASSICAL with the highest mean PSNR
    best = max(CLASSICAL, key=lambda k: s["stages"][k]["psnr_db"])
    assert s["best_classical"] == {"stage": best, **{k: s["stages"][best][k]
                                                     for k in ("psnr_db", "ssim")}}  # fmt: skip
    assert f"Best classical baseline: {best}" in page
    # ... and the best without the reference warp: the maps' renders and OpenCV alone
    maps = max(
        (c for c in CLASSICAL if c != "ref_inpaint"), key=lambda k: s["stages"][k]["psnr_db"]
    )
    assert "ref_inpaint" in CLASSICAL and s["best_classical_maps"]["stage"] == maps
    assert "map explains the view" in page and "Stages against ground truth" in page


def test_without_ground_truth_there_are_no_scores(tmp_path):
    out = RepairOutputs(tmp_path)
    out.on_decision(0, False, "sees little mapped surface (0.0% < 5.0%)", SCORE, CAM)
    out.on_renders(0, gs=img(10), alpha=np.zeros((H, W), np.float32))
    m = out.write()
    assert m["summary"]["stages"] == {} and m["views"][0]["metrics"] == {}
    assert m["summary"]["ground_truth"] is None


def test_an_unscored_run_makes_the_fallback_baselines_and_not_the_scoring_ones(tmp_path):
    valid = np.ones((H, W), bool)
    alpha = np.ones((H, W), np.float32)
    alpha[:, :8] = 0.0
    runs = {"plain": RepairOutputs(tmp_path / "plain"),  # no ground truth, no held-out frames
            "held-out": RepairOutputs(tmp_path / "held", None, {"holdout": range(0, 1)})}  # fmt: skip
    for out in runs.values():
        out.on_decision(0, True, "holes 25.0% > 2.0%", SCORE, CAM)
        out.on_renders(0, gs=img(90), alpha=alpha, mesh=img(110), valid=valid)
        out.write()
    files = {k: sorted(p.name for p in (out.out / "views" / "000").glob("*.png"))
             for k, out in runs.items()}  # fmt: skip
    assert "inpaint_ns.png" not in files["plain"] and "inpaint_fsr.png" not in files["plain"]
    assert {"mesh_fill.png", "inpaint.png", "mesh_inpaint.png"} <= set(files["plain"])
    assert set(files["held-out"]) == set(files["plain"]) | {"inpaint_ns.png", "inpaint_fsr.png"}
    assert not runs["plain"].scored and runs["held-out"].scored


def test_groups_are_scored_on_their_own(tmp_path):
    gt_dir = tmp_path / "gt"
    gt_dir.mkdir()
    out = RepairOutputs(tmp_path / "out", gt_dir, {"holdout": range(1, 3)})
    for i in range(3):
        g = img(60 + 40 * i, seed=i)
        cv2.imwrite(str(gt_dir / f"{i:03d}.png"), cv2.cvtColor(g, cv2.COLOR_RGB2BGR))
        out.on_decision(i, False, "map explains the view", SCORE, CAM)
        out.on_renders(i, gs=img(60 + 40 * i + 10, seed=9), alpha=np.ones((H, W), np.float32))
        out.on_final(i, g)
    m = out.write()
    per_view = [v["metrics"]["gs"]["psnr_db"] for v in m["views"]]
    groups = m["summary"]["groups"]
    assert groups["holdout"]["gs"]["views"] == 2 and groups["novel"]["gs"]["views"] == 1
    assert groups["holdout"]["gs"]["psnr_db"] == pytest.approx(np.mean(per_view[1:]))
    assert groups["novel"]["gs"]["psnr_db"] == pytest.approx(per_view[0])
    assert "holdout views" in (tmp_path / "out" / "report.html").read_text()
    # no mesh render: no region classes; the regions summary stays empty, per group too
    assert m["summary"]["regions"] == {} and set(m["summary"]["region_groups"]) == {
        "holdout",
        "novel",
    }


def test_a_skipped_view_keeps_the_3dgs_render_where_it_covers_and_fills_only_its_holes(run):
    out, gt, alpha, valid, d = run
    # a skipped view with holes: the 3DGS map misses columns :8, the mesh rows :4
    out.on_decision(2, False, "map explains the view (holes 1.0%, disagreement 0.0%)", SCORE, CAM)
    out.on_renders(2, gs=img(120), alpha=alpha, mesh=img(160), valid=valid)
    rec = out.views[2]
    covered = alpha >= 0.5
    # no measured choice: mesh fill + Telea, which is the 3DGS render wherever it covers
    got = out._stage_images(rec)["output_or_gs"]
    assert np.array_equal(got, rec.images["inpaint"])
    assert np.array_equal(got[covered], img(120)[covered])
    assert not np.array_equal(got[~covered], img(120)[~covered])  # its holes are filled
    # a run that measured the mesh better where both maps cover *repaired* views: a skipped
    # view still keeps its 3DGS render there; only the holes follow the choice
    out.fallback = {"per_region": {"both": "mesh_inpaint", "gs_only": "fixed",
                                   "mesh_only": "inpaint", "neither": "mesh_inpaint"},
                    "mse": {}, "pixels": {}, "samples": 1, "why": ""}  # fmt: skip
    got = out._stage_images(rec)["output_or_gs"]
    neither = ~covered & ~valid
    assert neither.sum() == 4 * 8
    assert np.array_equal(got[covered], img(120)[covered])
    assert np.array_equal(got[neither], rec.images["mesh_inpaint"][neither])
    assert np.array_equal(got[~covered & valid], rec.images["inpaint"][~covered & valid])
    assert not np.array_equal(rec.images["mesh_inpaint"][neither], rec.images["inpaint"][neither])


def test_a_skipped_view_within_the_held_out_frames_reach_follows_their_choice(tmp_path):
    h, w = 96, 128  # room for the seams' blend (fallback.FEATHER_PX)
    rng = np.random.default_rng(0)

    def im(value: int) -> np.ndarray:
        return np.clip(value + rng.integers(-20, 21, (h, w, 3)), 0, 255).astype(np.uint8)

    gt_dir = tmp_path / "gt"
    gt_dir.mkdir()
    out = RepairOutputs(tmp_path / "out", gt_dir)
    cam = {**CAM, "width": w, "height": h}
    alpha = np.ones((h, w), np.float32)
    alpha[:, :40] = 0.0  # the 3DGS map misses the left columns, the mesh the top rows
    valid = np.ones((h, w), bool)
    valid[:40] = False
    gs, mesh, fill = im(120), im(160), im(77)
    # two skipped views whose hole fills were distilled: view 0 near the keyframes, view 1 far
    for vid, dist in ((0, 0.2), (1, 2.5)):
        cv2.imwrite(str(gt_dir / f"{vid:03d}.png"), im(150))
        out.on_decision(vid, False, "map explains the view (holes 1.0%)", SCORE, cam, fill=True,
                        keyframe_distance_m=dist)  # fmt: skip
        out.on_renders(vid, gs=gs, alpha=alpha, mesh=mesh, valid=valid)
        out.on_filled(vid, fill)
        out.on_final(vid, np.clip(fill.astype(int) + rng.integers(-3, 4, fill.shape), 0, 255
                                  ).astype(np.uint8))  # fmt: skip
    near, far = out.views[0], out.views[1]
    # the held-out frames measured the mesh better where both maps cover, GSFixer where only
    # the 3DGS map does, and reach 0.5 m from a keyframe
    out.fallback = {"per_region": {"both": "mesh_inpaint", "gs_only": "fixed",
                                   "mesh_only": "inpaint", "neither": "mesh_inpaint"},
                    "mse": {}, "pixels": {}, "samples": 4, "why": ""}  # fmt: skip
    out.holdout_reach_m = 0.5
    m = out.write()
    views = {v["view"]: v for v in m["views"]}
    got = cv2.cvtColor(cv2.imread(str(tmp_path / "out/views/000/output.png")), cv2.COLOR_BGR2RGB)
    assert np.array_equal(got, near.images["output"])
    assert np.array_equal(out._stage_images(near)["output_or_gs"], got)
    r = regions(alpha, valid)
    off_seams = np.ones((25, 25), np.uint8)  # 3 sigmas of the blend and more
    both = cv2.erode((r == 0).astype(np.uint8), off_seams) > 0
    assert both.any() and np.array_equal(got[both], near.images["mesh_inpaint"][both])
    # GSFixer did not run on a skipped view: its regions take mesh fill + Telea
    gs_only = cv2.erode((r == 1).astype(np.uint8), off_seams) > 0
    assert gs_only.any() and np.array_equal(got[gs_only], near.images["inpaint"][gs_only])
    assert views["000"]["model"] == {
        "choice": {"both": "mesh_inpaint", "gs_only": "inpaint", "mesh_only": "inpaint",
                   "neither": "mesh_inpaint"},
        "choice_from": "held-out frames (skipped)",
    }  # fmt: skip
    # the map's fidelity is against what distillation fitted (the fill), not the 2D output
    fid = views["000"]["map_fidelity_db"]
    assert fid == pytest.approx(psnr(near.images["final"], fill)) and fid > 40
    assert psnr(near.images["final"], got) < 20
    # beyond the reach: the planner's fill stays the output; the 3DGS render where it covers
    covered = alpha >= 0.5
    assert np.array_equal(far.images["output"], fill) and views["001"]["model"] == {}
    assert np.array_equal(out._skipped_output(far)[covered], gs[covered])
    # no reach (the choice was the trainer's, not the held-out frames'): as beyond it
    out.holdout_reach_m = None
    assert out._near_choice(near) is None
    assert np.array_equal(out._skipped_output(near)[covered], gs[covered])


def test_every_stage_is_scored_per_region_class(run):
    out, gt, alpha, valid, d = run
    m = out.write()
    v0, v1 = m["views"]
    # view 0: the 3DGS map covers columns 8.., the mesh rows 4..: all four classes occur
    region = regions(alpha, valid)
    masks = {r: region == i for i, r in enumerate(REGIONS)}
    assert {r: int(k.sum()) for r, k in masks.items()} == {
        "both": 20 * 24,
        "gs_only": 4 * 24,
        "mesh_only": 20 * 8,
        "neither": 4 * 8,
    }
    assert set(v0["regions"]) == set(v0["metrics"]) == set(STAGES)
    stage_img = out._stage_images(out.views[0])
    for stage in ("gs", "inpaint_fsr", "fixed"):
        smap = ssim_map(stage_img[stage], gt[0]).numpy()
        for r in REGIONS:
            got = v0["regions"][stage][r]
            assert got["pixels"] == masks[r].sum()
            assert got["psnr_db"] == pytest.approx(
                psnr(stage_img[stage], gt[0], masks[r]), abs=1e-4
            )
            assert got["ssim"] == pytest.approx(smap[masks[r]].mean(), abs=1e-6)
    # view 1: alpha 1 everywhere, so only "both" and "gs_only"; the summary pools the two views
    assert set(v1["regions"]["gs"]) == {"both", "gs_only"}
    s = m["summary"]["regions"]
    assert set(s) == set(STAGES) and set(s["gs"]) == set(REGIONS)
    both = [v["regions"]["gs"]["both"] for v in (v0, v1)]
    n = both[0]["pixels"] + both[1]["pixels"]
    mse = sum(10 ** (-b["psnr_db"] / 10) * b["pixels"] for b in both) / n
    assert s["gs"]["both"]["pixels"] == n and s["gs"]["both"]["views"] == 2
    assert s["gs"]["both"]["psnr_db"] == pytest.approx(-10 * math.log10(mse), abs=1e-4)
    assert s["gs"]["both"]["ssim"] == pytest.approx(
        sum(b["ssim"] * b["pixels"] for b in both) / n, abs=1e-9
    )
    assert s["fixed"]["neither"]["views"] == 1 and s["gs"]["neither"]["views"] == 1
    page = (d / "report.html").read_text()
    assert "Error per region class (share of pixels: both" in page and "neither SSIM" in page


def test_map_fidelity_compares_the_final_map_with_what_was_delivered_without_ground_truth(
    tmp_path,
):
    out = RepairOutputs(tmp_path)  # no ground truth
    alpha = np.ones((H, W), np.float32)
    alpha[:, :8] = 0.0
    delivered = {}
    for vid, final_noise in ((0, 2), (1, 60)):  # view 1: the map lost what was delivered
        out.on_decision(vid, True, "holes 25.0% > 2.0%", SCORE, CAM)
        out.on_renders(vid, gs=img(90), alpha=alpha, mesh=img(110), valid=np.ones((H, W), bool))
        out.on_fixed(vid, img(100, seed=5), {"fix_s": 0.2}, {"version": 1, "step": 4})
        delivered[vid] = out.views[vid].images["output"]
        rng = np.random.default_rng(vid)
        noise = rng.integers(-final_noise, final_noise + 1, (H, W, 3))
        out.on_final(vid, np.clip(delivered[vid] + noise, 0, 255).astype(np.uint8))
    out.on_decision(2, False, "map explains the view (holes 0.0%)", SCORE, CAM)  # not distilled
    out.on_renders(2, gs=img(120), alpha=np.ones((H, W), np.float32))
    out.on_final(2, img(10))
    m = out.write()
    got = {v["view"]: v["map_fidelity_db"] for v in m["views"]}
    for vid in (0, 1):
        want = psnr(out.views[vid].images["final"], delivered[vid])
        assert got[f"{vid:03d}"] == pytest.approx(want)
    assert got["000"] > 35 and got["001"] < 20 and got["002"] is None
    fid = m["summary"]["map_fidelity"]
    assert fid["low"] == ["001"] and fid["median_db"] == pytest.approx(
        (got["000"] + got["001"]) / 2
    )


def test_map_sharpness_says_which_views_the_final_map_renders_blurrier_than_delivered(tmp_path):
    """View 000's final render is its output through the renderer's low-pass: what a map that
    holds the output exactly renders. It is not blurred, though it has less of the output's
    pixel grain (raw ratio 0.55 here); view 001's is veiled (a 3 px blur)."""
    import cv2

    from gsfix_online.core.metrics import sharpness
    from gsfix_online.mapping.splat.render_output import EPS2D

    out = RepairOutputs(tmp_path)  # no ground truth
    alpha = np.ones((H, W), np.float32)
    alpha[:, :8] = 0.0
    for vid, sigma in ((0, math.sqrt(EPS2D)), (1, 3.0)):
        out.on_decision(vid, True, "holes 25.0% > 2.0%", SCORE, CAM)
        out.on_renders(vid, gs=img(90), alpha=alpha, mesh=img(110), valid=np.ones((H, W), bool))
        out.on_fixed(vid, img(100, seed=5), {"fix_s": 0.2}, {"version": 1, "step": 4})
        delivered = out.views[vid].images["output"].astype(np.float32) / 255.0
        out.on_final(vid, cv2.GaussianBlur(delivered, (0, 0), sigma, borderType=cv2.BORDER_REFLECT))
    m = out.write()
    got = {v["view"]: v["map_sharpness"] for v in m["views"]}
    raw = {v["view"]: v["map_sharpness_raw"] for v in m["views"]}
    assert got["000"] == pytest.approx(1.0, abs=1e-3)
    held = out.views[0].images
    assert raw["000"] == pytest.approx(sharpness(held["final"]) / sharpness(held["output"]))
    assert raw["000"] < 0.6  # against the output itself, exactness reads as a blur
    blurred = out.views[1].images
    want = sharpness(blurred["final"]) / sharpness(blurred["output"], footprint_px2=EPS2D)
    assert got["001"] == pytest.approx(want) and got["001"] < 0.5
    assert raw["001"] < got["001"]
    assert m["summary"]["map_fidelity"]["blurred"] == ["001"]
    # the report's table of views says it beside the synthesised share, with no ground truth
    page = (tmp_path / "report.html").read_text()
    assert "map keeps dB" in page and "map sharpness" in page and "synthesised" in page
    assert f"<td>{got['001']:.3f}</td>" in page and "<td>1.000</td>" in page


def test_sharpness_is_the_mean_gradient_magnitude_of_the_luma():
    from gsfix_online.core.metrics import sharpness

    ramp = np.tile(np.arange(W, dtype=np.float32) / (W - 1), (H, 1))  # 1/(W-1) per pixel
    assert sharpness(ramp) == pytest.approx(1 / (W - 1), rel=1e-5)
    rgb = np.repeat((ramp * 255).round().astype(np.uint8)[..., None], 3, axis=2)
    assert sharpness(rgb) == pytest.approx(1 / (W - 1), rel=0.02)  # uint8: 0..255 -> 0..1
    assert sharpness(np.full((H, W, 3), 7, np.uint8)) == 0.0
    half = ramp.copy()
    half[:, W // 2 :] = 0.5  # flat on the right
    cols = np.tile(np.arange(W), (H, 1))
    assert sharpness(half, cols < W // 2 - 1) == pytest.approx(1 / (W - 1))  # the ramp's pixels
    assert sharpness(half, cols > W // 2) == 0.0  # the flat ones
    assert math.isnan(sharpness(half, np.zeros((H, W), bool)))
    with pytest.raises(ValueError, match="mask must be"):
        sharpness(half, np.ones((H, W + 1), bool))


def test_without_a_repair_the_writer_measures_the_fallbacks_on_the_held_out_frames(tmp_path):
    """The planner skipped every view (the map explains them), so no repair brought the run's
    measured choice: the writer measures the fallbacks per region on the held-out frames
    itself, and their output follows it (here the warp of the real frames, 3 levels off the
    truth, against renders 10-20 levels off)."""
    gt_dir = tmp_path / "gt"
    gt_dir.mkdir()
    out = RepairOutputs(tmp_path / "out", gt_dir, {"holdout": range(0, 2)})
    every = np.ones((H, W), bool)
    for vid in (0, 1):
        gt = img(100 + 20 * vid, seed=vid)
        cv2.imwrite(str(gt_dir / f"{vid:03d}.png"), cv2.cvtColor(gt, cv2.COLOR_RGB2BGR))
        out.on_decision(vid, False, "map explains the view", SCORE, CAM,
                        keyframe_distance_m=0.1 * (vid + 1))  # fmt: skip
        out.on_renders(vid, gs=img(90, seed=9), alpha=np.ones((H, W), np.float32),
                       mesh=img(110, seed=8), valid=every)  # fmt: skip
        out.on_ref(vid, np.clip(gt.astype(int) + 3, 0, 255).astype(np.uint8), every)
        out.on_final(vid, gt)
    m = out.write()
    fb = m["summary"]["fallback"]
    assert fb["why"].startswith("measured by the writer on the held-out frames")
    assert fb["per_region"]["both"] == "ref_inpaint" and out.holdout_reach_m == 0.2
    for v in m["views"]:
        got = v["metrics"]
        assert got["output_or_gs"] == got["ref_inpaint"] and got["ref_inpaint"]["psnr_db"] > 35
        assert got["inpaint"]["psnr_db"] < 30 and got["mesh_inpaint"]["psnr_db"] < 30
        assert v["model"]["choice_from"] == "held-out frames (skipped)"


def test_the_writer_composes_each_held_out_frame_by_the_other_frames_choice(tmp_path):
    """Frame 0's 3DGS render is exact and its warp 30 levels off; frame 1's warp is exact and
    its 3DGS render 40 off. Over both the warp measures best (the run's choice), but each
    frame is scored against its own image, so it follows the other frame's measurement:
    frame 1 takes the 3DGS render, not its exact warp."""
    gt_dir = tmp_path / "gt"
    gt_dir.mkdir()
    out = RepairOutputs(tmp_path / "out", gt_dir, {"holdout": range(0, 2)})
    every = np.ones((H, W), bool)

    def off(a: np.ndarray, d: int) -> np.ndarray:
        return np.clip(a.astype(int) + d, 0, 255).astype(np.uint8)

    for vid, (gs_off, ref_off) in enumerate(((0, 30), (40, 0))):
        gt = img(100, seed=vid)
        cv2.imwrite(str(gt_dir / f"{vid:03d}.png"), cv2.cvtColor(gt, cv2.COLOR_RGB2BGR))
        out.on_decision(vid, False, "map explains the view", SCORE, CAM,
                        keyframe_distance_m=0.1)  # fmt: skip
        out.on_renders(vid, gs=off(gt, gs_off), alpha=np.ones((H, W), np.float32),
                       mesh=off(gt, 60), valid=every)  # fmt: skip
        out.on_ref(vid, off(gt, ref_off), every)
        out.on_final(vid, gt)
    m = out.write()
    assert m["summary"]["fallback"]["per_region"]["both"] == "ref_inpaint"
    assert {v: c["per_region"]["both"] for v, c in out.fallback_without.items()} == {
        0: "ref_inpaint", 1: "inpaint"}  # fmt: skip
    views = {v["view"]: v["metrics"] for v in m["views"]}
    assert views["000"]["output_or_gs"] == views["000"]["ref_inpaint"]
    assert views["001"]["output_or_gs"] == views["001"]["inpaint"]
    assert views["001"]["output_or_gs"]["psnr_db"] < 20  # 40 levels off, where its warp is exact


def test_a_lone_held_out_frame_is_not_composed_by_a_choice_its_own_image_made(tmp_path):
    """One held-out frame: the writer's measurement on it picks its exact warp, but it is the
    frame that is scored, so it takes the recipe of no measurement (the 3DGS render, mesh fill
    and Telea), and the summary says that no other frame measured a choice for it."""
    gt_dir = tmp_path / "gt"
    gt_dir.mkdir()
    out = RepairOutputs(tmp_path / "out", gt_dir, {"holdout": range(0, 1)})
    every = np.ones((H, W), bool)
    gt = img(100, seed=0)
    cv2.imwrite(str(gt_dir / "000.png"), cv2.cvtColor(gt, cv2.COLOR_RGB2BGR))
    out.on_decision(0, False, "map explains the view", SCORE, CAM, keyframe_distance_m=0.1)
    off = np.clip(gt.astype(int) + 40, 0, 255).astype(np.uint8)
    # the 3DGS map misses the frame: all of it is mesh_only, where a skipped view would take
    # the measured choice (the 3DGS render is trusted only where it covers)
    out.on_renders(0, gs=off, alpha=np.zeros((H, W), np.float32), mesh=off, valid=every)
    out.on_ref(0, gt.copy(), every)
    out.on_final(0, gt)
    m = out.write()
    assert m["summary"]["fallback"]["per_region"]["mesh_only"] == "ref_inpaint"
    assert m["summary"]["fallback_without"] == {"000": None}
    got = m["views"][0]["metrics"]
    assert got["output_or_gs"] == got["inpaint"] and got["output_or_gs"]["psnr_db"] < 20


def test_a_baseline_equal_to_the_ground_truth_is_reported_with_an_infinite_psnr(tmp_path):
    """The real frames' warp can reproduce a held-out frame exactly: its PSNR is infinite,
    null in metrics.json, and the report says so instead of failing to format it."""
    gt_dir = tmp_path / "gt"
    gt_dir.mkdir()
    out = RepairOutputs(tmp_path / "out", gt_dir, {"holdout": range(0, 1)})
    every = np.ones((H, W), bool)
    gt = img(100)
    cv2.imwrite(str(gt_dir / "000.png"), cv2.cvtColor(gt, cv2.COLOR_RGB2BGR))
    out.on_decision(0, False, "map explains the view", SCORE, CAM, keyframe_distance_m=0.1)
    out.on_renders(0, gs=img(90, seed=9), alpha=np.ones((H, W), np.float32),
                   mesh=img(110, seed=8), valid=every)  # fmt: skip
    out.on_ref(0, gt, every)
    out.on_final(0, gt)
    m = out.write()
    best = m["summary"]["best_classical"]
    assert best["stage"] == "ref_inpaint" and best["psnr_db"] is None and best["ssim"] == 1.0
    assert "ref_inpaint (infinite PSNR, SSIM 1.000)" in (tmp_path / "out/report.html").read_text()


def test_without_opencvs_contrib_build_the_fsr_baseline_is_left_out_and_the_run_written(
    run, monkeypatch, caplog
):
    # a GPU image with the plain OpenCV build: the writer died at the end of the run before
    from gsfix_online.repair import baselines

    out, _, _, _, d = run
    monkeypatch.setattr(baselines, "FSR_FLAG", None)
    assert out.finish_baselines() == 0
    m = out.write()
    assert "FSR baseline left out" in caplog.text
    assert not list((d / "views").glob("*/inpaint_fsr.png"))
    assert (
        "inpaint_fsr" not in m["views"][0]["metrics"] and "inpaint_ns" in m["views"][0]["metrics"]
    )
    assert "inpaint_fsr" not in m["summary"]["stages"] and "output" in m["summary"]["stages"]
    assert json.loads((d / "metrics.json").read_text()) == m
