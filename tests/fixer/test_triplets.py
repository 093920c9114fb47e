"""Tests for gsfix_online/fixer/triplets.py: keyframe triplets and pretraining degradations."""

from __future__ import annotations

import numpy as np
import torch

from gsfix_online.fixer.triplets import (
    DegradeConfig,
    degrade_gs,
    degrade_mesh,
    relit_mesh_render,
    to_chw,
    triplet_from_keyframe,
)

H, W = 24, 32


def _gt(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.2, 0.8, (H, W, 3)).astype(np.float32)


def test_to_chw_gray_and_uint8():
    gray = np.full((H, W), 255, np.uint8)
    t = to_chw(gray)
    assert t.shape == (3, H, W) and t.dtype == torch.float32 and float(t.min()) == 1.0


def test_triplet_from_keyframe_with_and_without_mesh():
    alpha = np.ones((H, W), np.float32)
    alpha[4:12, 4:12] = 0
    arrays = {
        "color": (np.ones((H, W)) * 100).astype(np.uint8),  # grayscale camera
        "gs_render": np.zeros((H, W, 3), np.uint8),
        "gs_alpha": alpha,
    }
    t = triplet_from_keyframe(arrays, None)
    assert t.image_gt.shape == t.image_gs.shape == t.image_mesh.shape == (3, H, W)
    assert float(t.image_mesh.abs().max()) == 0  # no mesh: black
    assert len(t.alpha_holes) == 1 and t.alpha_holes[0][8, 8] and not t.alpha_holes[0][20, 20]
    mesh = np.full((H, W, 3), 51, np.uint8)
    torch.testing.assert_close(
        triplet_from_keyframe(arrays, mesh).image_mesh, torch.full((3, H, W), 0.2)
    )


def test_degrade_gs_holes_are_black_and_deterministic():
    cfg = DegradeConfig(gs_hole_prob=1.0, gs_noise=(0.0, 0.0), gs_blur=(0.0, 0.0))
    img, alpha = degrade_gs(_gt(), np.random.default_rng(3), cfg)
    img2, _ = degrade_gs(_gt(), np.random.default_rng(3), cfg)
    np.testing.assert_array_equal(img, img2)
    assert alpha.min() < 0.05 and alpha.max() == 1.0
    hole = alpha < 0.01
    assert np.abs(img[hole]).max() < 0.01  # background shows black
    keep = alpha > 0.999
    np.testing.assert_allclose(img[keep], _gt()[keep], atol=1e-3)  # no blur or noise asked


def test_degrade_gs_off_is_identity():
    cfg = DegradeConfig(gs_hole_prob=0.0, gs_noise=(0.0, 0.0), gs_blur=(0.0, 0.0))
    img, alpha = degrade_gs(_gt(), np.random.default_rng(0), cfg)
    np.testing.assert_allclose(img, _gt(), atol=1e-6)
    assert alpha.min() == 1.0


def test_degrade_mesh_blurs_gt_or_uses_the_mesh():
    cfg = DegradeConfig(mesh_noise=0.0)
    gt = _gt()
    blurred = degrade_mesh(gt, np.random.default_rng(0), cfg)
    assert blurred.std() < 0.5 * gt.std()  # heavy blur removes the per-pixel noise
    mesh = np.full((H, W, 3), 0.5, np.float32)
    valid = np.ones((H, W), bool)
    valid[:, :4] = False
    out = degrade_mesh(gt, np.random.default_rng(0), cfg, mesh, valid)
    assert np.all(out[:, :4] == 0) and np.allclose(out[:, 4:], 0.5)


def test_relit_mesh_render_puts_the_light_back():
    albedo = np.full((H, W, 3), 0.5, np.float32)
    gt = albedo * 0.6  # uniformly darker light
    out = relit_mesh_render(albedo, gt, np.ones((H, W), bool))
    np.testing.assert_allclose(out, gt, atol=1e-5)
