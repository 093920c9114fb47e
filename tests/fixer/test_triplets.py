"""Tests for gsfix_online/fixer/triplets.py: keyframe triplets and pretraining degradations."""

from __future__ import annotations

import numpy as np
import torch

from gsfix_online.fixer.triplets import (
    DegradeConfig,
    degrade_gs,
    degrade_mesh,
    relit_mesh_render,
    render_seen_from,
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


def _plane_views() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A fronto-parallel plane at z = 2 m whose colour is its world x (a ramp): K, the keyframe
    pose (identity), its depth, and a source camera moved 0.5 m along x."""
    K = np.array([[20.0, 0, (W - 1) / 2], [0, 20.0, (H - 1) / 2], [0, 0, 1]])
    T_src = np.eye(4)
    T_src[0, 3] = 0.5
    return K, np.eye(4), np.full((H, W), 2.0, np.float32), T_src


def _ramp_render(K: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """The plane seen from ``T_world_cam`` (a translation): red = 100 + 40 * world x, uint8."""
    u = np.arange(W)
    x_world = (u - K[0, 2]) / K[0, 0] * 2.0 + T_world_cam[0, 3]
    img = np.zeros((H, W, 3), np.uint8)
    img[:, :, 0] = np.rint(100 + 40 * x_world)[None, :]
    img[:, :, 1] = 50
    return img


def test_render_seen_from_the_same_pose_is_the_render():
    K, T, depth, _ = _plane_views()
    render = np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8)
    depth[3:6, 4:9] = 0  # no depth: black
    out = render_seen_from(render, K, T, depth, K, T)
    np.testing.assert_array_equal(out[depth > 0], render[depth > 0])
    assert not out[depth == 0].any()


def test_render_seen_from_a_moved_camera_lands_on_the_same_surface_points():
    K, T, depth, T_src = _plane_views()
    out = render_seen_from(_ramp_render(K, T_src), K, T_src, depth, K, T)
    # each keyframe pixel shows the colour of its own world point, as seen from the source;
    # the source sees world x in [-1.05, 2.05] m, the keyframe [-1.55, 1.55] m
    want = _ramp_render(K, T)
    x_world = (np.arange(W) - K[0, 2]) / K[0, 0] * 2.0
    seen = x_world >= -1.0  # a pixel's margin for the bilinear border
    assert seen.sum() == W - 6
    assert np.abs(out[:, seen].astype(int) - want[:, seen]).max() <= 1
    assert not out[:, x_world < -1.05].any()  # outside the source image: black


def test_triplet_from_keyframe_carries_the_novel_renders():
    novel = np.zeros((2, H, W, 3), np.uint8)
    novel[1] = 255
    arrays = {
        "color": np.zeros((H, W, 3), np.uint8),
        "gs_render": np.zeros((H, W, 3), np.uint8),
        "gs_alpha": np.ones((H, W), np.float32),
        "novel_render": novel,
    }
    t = triplet_from_keyframe(arrays, None)
    assert len(t.gs_novel) == 2 and t.gs_novel[1].shape == (3, H, W)
    assert float(t.gs_novel[0].max()) == 0 and float(t.gs_novel[1].min()) == 1
    assert triplet_from_keyframe({k: arrays[k] for k in list(arrays)[:3]}, None).gs_novel == []
