"""Tests for gsfix_online/fixer/masks.py."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from gsfix_online.fixer.config import MaskConfig
from gsfix_online.fixer.masks import (
    MaskDraw,
    alpha_hole_mask,
    apply_masks,
    disocclusion_mask,
    draw_masks,
    procedural_mask,
)


@pytest.mark.parametrize(("p_shared", "p_gs"), [(0.3, 0.3), (0.1, 0.7), (0.0, 1.0)])
def test_masks_respect_probabilities(p_shared, p_gs):
    cfg = MaskConfig(p_shared=p_shared, p_gs_only=p_gs)
    rng = np.random.default_rng(0)
    n = 2000
    draws = [draw_masks(cfg, rng, 24, 32) for _ in range(n)]
    shared = np.array([d.shared is not None for d in draws])
    gs = np.array([d.gs_only is not None for d in draws])
    for freq, p in (
        (shared.mean(), p_shared),
        (gs.mean(), p_gs),
        ((shared & gs).mean(), p_shared * p_gs),
    ):
        sigma = math.sqrt(p * (1 - p) / n)
        assert abs(freq - p) <= 4.5 * sigma + 1e-12, (freq, p)


def test_disabled_policy_draws_nothing():
    cfg = MaskConfig(enabled=False, p_shared=1.0, p_gs_only=1.0)
    assert draw_masks(cfg, np.random.default_rng(0), 8, 8) == MaskDraw(None, None)


def test_procedural_mask_area_and_seed():
    cfg = MaskConfig(shape_area=(0.05, 0.15))
    areas = []
    for s in range(20):
        m = procedural_mask(np.random.default_rng(s), 120, 160, cfg)
        assert m.dtype == np.bool_ and m.shape == (120, 160)
        areas.append(m.mean())
    # Pieces overlap and leave the image, so areas fall below the drawn value, rarely above.
    assert 0.01 < np.median(areas) < 0.2 and max(areas) < 0.3
    a = procedural_mask(np.random.default_rng(7), 60, 80, cfg)
    assert np.array_equal(a, procedural_mask(np.random.default_rng(7), 60, 80, cfg))


def test_blur_only_on_the_gs_mask():
    h, w = 40, 60
    mask = np.zeros((h, w), bool)
    mask[10:30, 20:40] = True
    cfg = MaskConfig(blur_sigma_frac=0.05)
    mesh, gs = torch.ones(3, h, w), torch.ones(3, h, w)
    out_mesh, out_gs = apply_masks(mesh, gs, MaskDraw(mask, None), cfg)
    # mesh: a hard mask, exactly 0 inside and 1 outside
    assert torch.equal(out_mesh[0], torch.from_numpy(~mask).float())
    # gs: soft edges, values strictly between 0 and 1 along the border
    assert ((out_gs > 0.05) & (out_gs < 0.95)).sum() > 0
    assert out_gs[0, 20, 30] < 0.05 and out_gs[0, 0, 0] > 0.99
    # a gs-only mask leaves the mesh image untouched
    out_mesh2, out_gs2 = apply_masks(mesh, gs, MaskDraw(None, mask), cfg)
    assert torch.equal(out_mesh2, mesh)
    torch.testing.assert_close(out_gs2, out_gs)


def test_mesh_only_mask_is_hard_on_the_mesh_and_drawn_with_its_probability():
    h, w = 40, 60
    mask = np.zeros((h, w), bool)
    mask[10:30, 20:40] = True
    mesh, gs = torch.ones(3, h, w), torch.ones(3, h, w)
    out_mesh, out_gs = apply_masks(mesh, gs, MaskDraw(None, None, mask), MaskConfig())
    assert torch.equal(out_mesh[1], torch.from_numpy(~mask).float()) and torch.equal(out_gs, gs)
    cfg = MaskConfig(p_shared=0.5, p_gs_only=0.5, p_mesh_only=0.3)
    rng = np.random.default_rng(0)
    n = 2000
    freq = np.mean([draw_masks(cfg, rng, 24, 32).mesh_only is not None for _ in range(n)])
    assert abs(freq - 0.3) <= 4.5 * math.sqrt(0.3 * 0.7 / n)
    assert all(draw_masks(MaskConfig(), rng, 24, 32).mesh_only is None for _ in range(50))


def test_switched_off_sources_are_not_used():
    h, w = 16, 20
    cand = np.zeros((h, w), bool)
    cand[2:6, 3:9] = True
    cfg = MaskConfig(p_shared=1.0, p_gs_only=1.0, use_shapes=False, use_alpha_holes=False)
    rng = np.random.default_rng(1)
    for _ in range(20):
        d = draw_masks(cfg, rng, h, w, disocclusions=[cand], alpha_holes=[~cand])
        for m in (d.shared, d.gs_only):
            assert np.array_equal(m, cand) or np.array_equal(m, cand[:, ::-1])
    with pytest.raises(ValueError, match="bool"):
        draw_masks(cfg, rng, h, w, disocclusions=[cand.astype(np.uint8)])


def _K(f, w, h):
    return np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]], np.float64)


def test_disocclusion_identity_pose_covers_everything():
    h, w = 30, 40
    depth = np.full((h, w), 2.0, np.float32)
    K, T = _K(30, w, h), np.eye(4)
    assert not disocclusion_mask(depth, K, T, K, T, h, w).any()


def test_disocclusion_analytic_plane_shift():
    """A plane at z = 2 seen by a camera moved 0.4 m right: the right columns are uncovered."""
    h, w, f, z, tx = 30, 40, 30.0, 2.0, 0.4
    depth = np.full((h, w), z, np.float32)
    K = _K(f, w, h)
    T_src, T_tgt = np.eye(4), np.eye(4)
    T_tgt[0, 3] = tx
    # Source pixels land f * tx / z = 6 px to the left: target columns u > w - 1 - 6 get none.
    expected = np.broadcast_to(np.arange(w) > (w - 1) - f * tx / z, (h, w))
    for close_px in (0, 1):
        hole = disocclusion_mask(depth, K, T_src, K, T_tgt, h, w, close_px=close_px)
        assert np.array_equal(hole, expected)


def test_disocclusion_closing_fills_forward_warp_cracks():
    """Half-pixel shifts leave every other column empty; the closing fills those cracks."""
    h, w, f = 30, 40, 30.0
    depth = np.full((h, w), 2.0, np.float32)
    K, T_tgt = _K(f, w, h), np.eye(4)
    T_tgt[0, 3] = 0.5  # 7.5 px
    cracked = disocclusion_mask(depth, K, np.eye(4), K, T_tgt, h, w, close_px=0)
    closed = disocclusion_mask(depth, K, np.eye(4), K, T_tgt, h, w, close_px=1)
    assert cracked[:, :30].any() and not closed[:, :30].any()
    assert closed[:, 33:].all()


def test_disocclusion_ignores_invalid_depth_and_points_behind():
    h, w = 10, 12
    depth = np.zeros((h, w), np.float32)
    K = _K(10, w, h)
    assert disocclusion_mask(depth, K, np.eye(4), K, np.eye(4), h, w).all()
    T_tgt = np.diag([-1.0, 1.0, -1.0, 1.0])  # turned around: everything behind
    depth[:] = 1.0
    assert disocclusion_mask(depth, K, np.eye(4), K, T_tgt, h, w).all()


def test_alpha_hole_mask():
    alpha = np.ones((20, 20), np.float32)
    alpha[5:12, 4:10] = 0.1
    alpha[17, 17] = 0.0  # a speck: removed by the opening
    hole = alpha_hole_mask(alpha, threshold=0.5)
    expected = np.zeros((20, 20), bool)
    expected[5:12, 4:10] = True
    assert np.array_equal(hole, expected)
    assert alpha_hole_mask(alpha, 0.5, open_px=0)[17, 17]


def test_mask_config_validation():
    with pytest.raises(ValueError, match="shape_area"):
        dataclasses.replace(MaskConfig(), shape_area=(0.3, 0.1)).validate()


def test_perturbed_pose_stays_within_its_bounds():
    from gsfix_online.fixer.masks import perturbed_pose

    rng = np.random.default_rng(0)
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    for _ in range(50):
        P = perturbed_pose(T, rng, max_deg=20.0, max_m=0.25)
        R = P[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        angle = np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
        assert 0.3 * 20.0 - 1e-9 <= angle <= 20.0 + 1e-9
        assert np.linalg.norm(P[:3, 3] - T[:3, 3]) <= 0.25 + 1e-12
        np.testing.assert_array_equal(P[3], [0, 0, 0, 1])
    assert np.array_equal(
        perturbed_pose(T, np.random.default_rng(1)), perturbed_pose(T, np.random.default_rng(1))
    )


def test_informative_hole_keeps_partial_holes_only():
    from gsfix_online.fixer.masks import informative_hole

    alpha = np.ones((40, 60), np.float32)
    assert informative_hole(alpha) is None  # no hole: nothing to learn
    alpha[:, :20] = 0.0
    hole = informative_hole(alpha)
    assert hole is not None and hole.dtype == bool and abs(hole.mean() - 1 / 3) < 1e-6
    assert informative_hole(np.zeros_like(alpha)) is None  # the pose looked away from the map
