"""Growth on analytic scenes: a fronto-parallel checkerboard plane at z = 2 m."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gsfix_online.core.config import ConfigError, build
from gsfix_online.core.se3 import look_at
from gsfix_online.core.types import Intrinsics, RGBDFrame, make_frame
from gsfix_online.mapping.splat.gaussians import SH_C0, GaussianMap
from gsfix_online.mapping.splat.growth import GrowthConfig, grow, quadtree_cells

W, H, F, Z = 64, 48, 50.0, 2.0
K = Intrinsics(F, F, (W - 1) / 2, (H - 1) / 2, W, H)
POSE = look_at([1.0, 2.0, 0.5], [3.0, 1.0, 1.5])
CFG = GrowthConfig(max_cell_px=16, min_cell_px=2, var_thresh=0.002)


def checker_plane(square_px: int = 4, gray: bool = False, split: bool = True) -> RGBDFrame:
    """Checkerboard on the left half (if ``split``), flat grey on the right; depth 2 m everywhere."""
    v, u = np.mgrid[0:H, 0:W]
    img = np.where(((u // square_px) + (v // square_px)) % 2 == 0, 230, 20).astype(np.uint8)
    if split:
        img[:, W // 2 :] = 128
    color = img if gray else np.stack([img, img // 2, 255 - img], axis=2)
    depth = np.full((H, W), Z, np.float32)
    return make_frame(color, depth, K, POSE, 0)


def cam_points(means: np.ndarray) -> np.ndarray:
    R, t = POSE[:3, :3], POSE[:3, 3]
    return (means.astype(np.float64) - t) @ R


@pytest.mark.parametrize("gray", [False, True])
def test_plane_positions_scales_colours(gray: bool) -> None:
    frame = checker_plane(gray=gray)
    res = grow(frame, CFG)
    assert len(res) == res.n_cells > 0 and res.n_explained == 0 and res.n_invalid_depth == 0
    p = cam_points(res.means)
    np.testing.assert_allclose(p[:, 2], Z, atol=1e-5)  # on the plane z_cam = 2
    y0, x0, h, w = res.cells.T
    np.testing.assert_allclose(p[:, 0], (x0 + (w - 1) / 2 - K.cx) / F * Z, atol=1e-5)
    np.testing.assert_allclose(p[:, 1], (y0 + (h - 1) / 2 - K.cy) / F * Z, atol=1e-5)
    # scale = depth x half-diagonal / f, isotropic
    half_diag = 0.5 * np.hypot(w, h)
    np.testing.assert_allclose(
        np.exp(res.log_scales), (Z * half_diag / F)[:, None].repeat(3, 1), rtol=1e-6
    )
    np.testing.assert_allclose(1 / (1 + np.exp(-res.opacity_logits)), 0.5)
    np.testing.assert_array_equal(res.quats, np.tile([1.0, 0, 0, 0], (len(res), 1)))
    assert res.sh0.shape == (len(res), 1, 1 if gray else 3)
    # leaves are uniform, so their colour is exactly the pixels' colour
    rgb = 0.5 + SH_C0 * res.sh0[:, 0]
    color = frame.color.reshape(H, W, -1)[y0, x0] / 255.0
    np.testing.assert_allclose(rgb, color, atol=1e-6)


def test_more_gaussians_in_high_variance_regions() -> None:
    res = grow(checker_plane(square_px=4), CFG)
    left = res.cells[:, 1] < W // 2
    assert np.count_nonzero(left) == (W // 2) * H // 16  # 4x4 leaves on the checkerboard
    assert np.count_nonzero(~left) == (W // 2) * H // 256  # 16x16 roots on flat grey
    assert set(res.cells[left, 2]) == {4} and set(res.cells[~left, 2]) == {16}


def test_quadtree_covers_image_once_on_odd_sizes() -> None:
    rng = np.random.default_rng(0)
    img = rng.random((37, 53, 3)).astype(np.float32)
    cells = quadtree_cells(img, max_cell_px=16, min_cell_px=3, var_thresh=0.0)
    cover = np.zeros((37, 53), int)
    for y0, x0, h, w in cells:
        cover[y0 : y0 + h, x0 : x0 + w] += 1
    assert (cover == 1).all()
    assert cells[:, 2:].min() >= 1 and cells[:, 2:].max() <= 5  # split while >= 2 * min_cell_px


def test_nothing_added_where_render_explains() -> None:
    frame = checker_plane()
    color = frame.color / 255.0
    res = grow(frame, CFG, alpha=np.ones((H, W), np.float32), rendered=color.astype(np.float32))
    assert len(res) == 0 and res.n_explained == res.n_cells


def test_added_only_where_new_or_badly_rendered() -> None:
    frame = checker_plane(split=False)
    color = (frame.color / 255.0).astype(np.float32)
    alpha = np.ones((H, W, 1), np.float32)
    alpha[:, :16] = 0.0  # columns 0..15 newly observed
    rendered = color.copy()
    rendered[32:, 48:] = 1.0 - rendered[32:, 48:]  # bottom-right badly rendered
    res = grow(frame, CFG, alpha=alpha, rendered=rendered)
    y0, x0, h, w = res.cells.T
    cy, cx = y0 + h / 2, x0 + w / 2
    assert len(res) > 0
    assert np.all((cx < 16) | ((cx > 48) & (cy > 32)))
    assert np.any(cx < 16) and np.any(cx > 48)
    # colour error below the threshold does not count
    res = grow(frame, CFG, alpha=np.ones((H, W)), rendered=np.clip(color + 0.05, 0, 1))
    assert len(res) == 0


def test_invalid_depth_gives_no_gaussians() -> None:
    frame = checker_plane()
    depth = frame.depth.copy()
    depth[:, : W // 2] = 0.0
    half = dataclasses.replace(frame, depth=depth)
    res = grow(half, CFG)
    assert np.all(res.cells[:, 1] >= W // 2) and res.n_invalid_depth > 0
    nan = dataclasses.replace(frame, depth=np.full((H, W), np.nan, np.float32))
    res = grow(nan, CFG)
    assert len(res) == 0 and res.n_invalid_depth == res.n_cells
    far = dataclasses.replace(frame, depth=np.full((H, W), 50.0, np.float32))
    assert len(grow(far, CFG)) == 0  # beyond max_depth_m


def test_result_feeds_gaussian_map() -> None:
    res = grow(checker_plane(gray=True), CFG)
    gmap = GaussianMap(sh_degree=2, channels=1)
    gmap.add(res.means, res.log_scales, res.quats, res.opacity_logits, res.sh0)
    assert len(gmap) == len(res)
    np.testing.assert_array_equal(gmap.means.detach().numpy(), res.means)


def test_validation() -> None:
    frame = checker_plane()
    with pytest.raises(ValueError, match=r"alpha must be \[48, 64\]"):
        grow(frame, CFG, alpha=np.ones((10, 10), np.float32))
    with pytest.raises(ValueError, match=r"rendered must be \[48, 64, 3\]"):
        grow(frame, CFG, alpha=np.ones((H, W), np.float32), rendered=np.ones((H, W), np.float32))
    with pytest.raises(ValueError, match="alpha must be floating point"):
        grow(frame, CFG, alpha=np.ones((H, W), np.uint8))
    with pytest.raises(TypeError, match="frame must be an RGBDFrame"):
        grow(frame.color, CFG)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="min_cell_px 8 exceeds max_cell_px 4"):
        build(GrowthConfig, overrides=["min_cell_px=8", "max_cell_px=4"])
    with pytest.raises(ConfigError, match="init_opacity: value 1.0 is out of range"):
        build(GrowthConfig, overrides=["init_opacity=1.0"])


def test_grown_plane_renders_at_its_depth() -> None:
    """Round trip through the renderer: the seeded plane covers the view at depth 2 m."""
    import torch

    from gsfix_online.mapping.splat.render import render

    frame = checker_plane()
    res = grow(frame, CFG)
    gmap = GaussianMap(sh_degree=0, channels=3)
    gmap.add(res.means, res.log_scales, res.quats, res.opacity_logits, res.sh0)
    out = render(
        gmap.means, gmap.params["quats"], gmap.scales, gmap.opacities, gmap.sh, None,
        torch.tensor(K.K, dtype=torch.float32), W, H,
        T_world_cam=torch.tensor(POSE, dtype=torch.float32), sh_degree=0, backend="cpu",
    )  # fmt: skip
    alpha, depth = out.alpha.detach().numpy(), out.depth.detach().numpy()
    # overlapping opacity-0.5 Gaussians; the image border sees only half of its neighbours
    assert alpha.min() > 0.4 and alpha[8:-8, 8:-8].min() > 0.6
    np.testing.assert_allclose(depth[alpha > 0.1], Z, atol=1e-4)
    # the flat right half renders its own grey (128/255 in every channel after alpha)
    right = out.color.detach().numpy()[8:-8, W // 2 + 8 : -8] / alpha[8:-8, W // 2 + 8 : -8, None]
    np.testing.assert_allclose(right, frame.color[8:-8, W // 2 + 8 : -8] / 255.0, atol=2e-3)
