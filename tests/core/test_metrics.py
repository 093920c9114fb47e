"""PSNR and SSIM on analytic pairs, and their input checks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gsfix_online.core.metrics import (
    MaskedScores,
    edge_gain,
    masked_scores,
    pooled,
    psnr,
    region_headroom,
    scores,
    sharpness,
    ssim,
)


def test_psnr_analytic_value_uint8_and_float_agree():
    a = np.full((8, 10, 3), 100, np.uint8)
    b = a.copy()
    b[..., 0] += 10  # error 10/255 on one channel of three -> mse = (10/255)^2 / 3
    expected = -10 * math.log10((10 / 255) ** 2 / 3)
    assert psnr(b, a) == pytest.approx(expected, rel=1e-5)
    assert psnr(b.astype(np.float32) / 255, a.astype(np.float32) / 255) == pytest.approx(
        expected, rel=1e-5
    )


def test_psnr_identical_is_inf_and_mask_selects_pixels():
    a = np.zeros((4, 4), np.uint8)
    b = a.copy()
    b[0, 0] = 255
    assert psnr(a, a) == math.inf
    mask = np.zeros((4, 4), bool)
    mask[2:, 2:] = True
    assert psnr(b, a, mask) == math.inf
    assert psnr(b, a) == pytest.approx(10 * math.log10(16), rel=1e-6)
    assert math.isnan(psnr(b, a, np.zeros((4, 4), bool)))


def test_ssim_identical_is_one_and_noise_lowers_it():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (32, 32), dtype=np.uint8)
    noisy = np.clip(img + rng.normal(0, 40, img.shape), 0, 255).astype(np.uint8)
    assert ssim(img, img) == pytest.approx(1.0, abs=1e-6)
    s = scores(noisy, img)
    assert 0.0 < s.ssim < 0.9 and 5.0 < s.psnr_db < 25.0


@pytest.mark.parametrize(
    ("a", "b", "match"),
    [
        (np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4), np.uint8), "same shape"),
        (np.zeros((4, 4, 2), np.uint8), np.zeros((4, 4, 2), np.uint8), r"\[H, W, 1\|3\]"),
        (np.zeros((4, 4), np.int32), np.zeros((4, 4), np.int32), "uint8 or floating"),
    ],
)
def test_bad_inputs_raise_one_line_errors(a, b, match):
    with pytest.raises(ValueError, match=match):
        psnr(a, b)


# float32 SSIM on the CPU: a flat pair measured 1.6e-4 off its analytic value (the filtering)
SSIM_F32_ATOL = 5e-4


def test_masked_scores_analytic_values_per_region():
    target = np.full((12, 16, 3), 0.5, np.float32)
    pred = target.copy()
    pred[:, :6, 0] += 0.3  # left: one channel of three off by 0.3 -> mse 0.09 / 3 = 0.03
    pred[:, 6:, :] += 0.01  # right: every channel off by 0.01 -> mse 1e-4
    left = np.zeros((12, 16), bool)
    left[:, :6] = True
    got = masked_scores(pred, target, {"left": left, "right": ~left, "none": np.zeros_like(left)})
    assert set(got) == {"left", "right"}  # a mask without pixels is left out
    assert got["left"].pixels == 72 and got["right"].pixels == 120
    assert got["left"].mse == pytest.approx(0.03, rel=1e-5)
    assert got["left"].psnr_db == pytest.approx(-10 * math.log10(0.03), rel=1e-5)
    assert got["right"].psnr_db == pytest.approx(40.0, abs=1e-3)


def test_masked_ssim_of_a_flat_pair_is_the_analytic_luminance_term():
    a, b, c1 = 0.6, 0.5, 0.01**2  # no variance: SSIM = (2ab + C1) / (a^2 + b^2 + C1)
    pred, target = np.full((12, 16), a, np.float32), np.full((12, 16), b, np.float32)
    top = np.zeros((12, 16), bool)
    top[:3] = True
    got = masked_scores(pred, target, {"top": top, "rest": ~top})
    want = (2 * a * b + c1) / (a * a + b * b + c1)
    for m in got.values():
        assert m.ssim == pytest.approx(want, abs=SSIM_F32_ATOL)


def test_pooled_weights_each_pixel_the_same():
    # 4 px at mse 0.01 and 12 px at mse 1e-4: pooled mse (0.04 + 0.0012) / 16 = 0.002575
    a = MaskedScores(20.0, 0.5, 0.01, 4)
    b = MaskedScores(40.0, 0.9, 1e-4, 12)
    p = pooled([a, b])
    assert p.pixels == 16 and p.mse == pytest.approx(0.002575)
    assert p.psnr_db == pytest.approx(-10 * math.log10(0.002575))
    assert p.ssim == pytest.approx((4 * 0.5 + 12 * 0.9) / 16)
    assert pooled([]) is None
    assert pooled([MaskedScores(math.inf, 1.0, 0.0, 3)]).psnr_db == math.inf


@pytest.mark.parametrize(
    ("mask", "match"),
    [
        (np.zeros((4, 5), bool), r"^mask 'm' must be bool \[H, W\] = \[4, 4\], got bool \[4, 5\]$"),
        (np.zeros((4, 4), np.uint8), r"^mask 'm' must be bool .*, got uint8 \[4, 4\]$"),
        ([[True] * 4] * 4, r"^mask 'm' must be bool .*, got list$"),
    ],
)
def test_masked_scores_rejects_bad_masks(mask, match):
    with pytest.raises(ValueError, match=match):
        masked_scores(np.zeros((4, 4), np.uint8), np.zeros((4, 4), np.uint8), {"m": mask})


def test_block_gradient_ratio_analytic_values():
    from gsfix_online.core.metrics import block_gradient_ratio

    rng = np.random.default_rng(0)
    noise = rng.random((96, 128, 3))
    blocks = np.kron(rng.random((24, 32, 3)), np.ones((4, 4, 1)))  # constant 4x4 blocks
    # white noise has no preferred grid (1 within sampling error, 24k pairs across)
    assert abs(block_gradient_ratio(noise, 4) - 1) < 0.03
    # constant blocks differ only across their boundaries; on another grid they show too
    assert block_gradient_ratio(blocks, 4) == np.inf
    assert block_gradient_ratio(blocks, 4, offset=2) == 0.0
    # a linear ramp has the same step everywhere: exactly 1, in uint8 too
    ramp = np.tile(np.arange(128, dtype=np.uint8), (64, 1))
    assert block_gradient_ratio(ramp, 4) == pytest.approx(1.0, abs=1e-6)  # float32 steps
    # half noise, half blocks (both uniform): across a boundary both step, inside only the noise
    assert block_gradient_ratio(0.5 * noise + 0.5 * blocks, 4) == pytest.approx(2.0, rel=0.05)
    assert np.isnan(block_gradient_ratio(np.full((8, 8), 0.5), 4))
    with pytest.raises(ValueError, match="block must be >= 2"):
        block_gradient_ratio(noise, 1)


def test_region_headroom_matches_the_images_it_describes():
    rng = np.random.default_rng(3)
    target = rng.random((24, 32, 3)).astype(np.float32)
    pred = np.clip(target + rng.normal(0, 0.1, target.shape), 0, 1).astype(np.float32)
    region = np.zeros((24, 32), np.uint8)
    region[:, 20:] = 1
    pred[:, 20:] = 0.5  # region 1 holds a flat guess, region 2 has no pixels
    room = region_headroom(pred, target, region, ["seen", "hole", "empty"])
    assert set(room) == {"seen", "hole"}
    base = psnr(pred, target)
    err = ((pred - target) ** 2).mean(-1)
    for i, name in enumerate(["seen", "hole"]):
        sel = region == i
        h = room[name]
        assert h.pixel_share == pytest.approx(sel.mean())
        assert h.error_share == pytest.approx(err[sel].sum() / err.sum(), rel=1e-5)
        exact = np.where(sel[..., None], target, pred)
        assert h.exact_gain_db == pytest.approx(psnr(exact, target) - base, abs=1e-4)
        flat = np.where(sel[..., None], target[sel].mean(0), pred)
        assert h.mean_fill_gain_db == pytest.approx(psnr(flat, target) - base, abs=1e-4)
    assert room["hole"].mean_fill_gain_db > 0  # the mean beats 0.5 on uniform noise
    assert room["seen"].mean_fill_gain_db < 0  # and loses to a close prediction
    assert room["seen"].error_share + room["hole"].error_share == pytest.approx(1.0)
    exact = region_headroom(target, target, region, ["seen", "hole"])
    assert exact["hole"].exact_gain_db == 0.0 and exact["hole"].error_share == 0.0
    with pytest.raises(ValueError, match="region must be"):
        region_headroom(pred, target, region[:, :5], ["seen"])


def test_sharpness_through_a_footprint_is_that_of_the_blurred_image():
    import cv2

    rng = np.random.default_rng(3)
    grain = rng.uniform(0.2, 0.8, (24, 32, 3)).astype(np.float32)
    blurred = cv2.GaussianBlur(grain, (0, 0), math.sqrt(0.3), borderType=cv2.BORDER_REFLECT)
    assert sharpness(grain, footprint_px2=0.3) == pytest.approx(sharpness(blurred), rel=1e-6)
    assert sharpness(grain, footprint_px2=0.3) < 0.6 * sharpness(grain)  # pixel grain loses most
    assert sharpness(grain, footprint_px2=0.0) == sharpness(grain)
    u8 = (grain * 255).round().astype(np.uint8)  # uint8 reads as [0, 1]
    assert sharpness(u8, footprint_px2=0.3) == pytest.approx(sharpness(blurred), rel=0.01)
    ramp = np.tile(np.arange(32, dtype=np.float32) / 31, (24, 1))  # a ramp keeps its slope
    inner = np.zeros((24, 32), bool)
    inner[:, 3:-3] = True
    assert sharpness(ramp, inner, footprint_px2=0.3) == pytest.approx(1 / 31, rel=1e-4)
    with pytest.raises(ValueError, match="footprint_px2 must be >= 0"):
        sharpness(grain, footprint_px2=-0.1)


def test_edge_gain_tells_a_blur_from_removed_grain():
    import cv2

    rng = np.random.default_rng(0)
    truth = np.zeros((48, 64), np.float32)
    truth[:, 32:] = 0.8  # one vertical edge
    truth[20:28, 8:16] = 0.5  # and a square
    assert edge_gain(truth, truth) == pytest.approx(1.0)
    assert edge_gain(0.5 * truth, truth) == pytest.approx(0.5)  # half the contrast: a veil
    # a 1-px Gaussian blur spreads each step over its neighbours: the mean gradient magnitude
    # (a step's total variation) barely moves, 0.977 here, the gain on the truth's edges, 0.629
    blurred = cv2.GaussianBlur(truth, (0, 0), 1.0)
    assert sharpness(blurred) / sharpness(truth) > 0.95
    assert 0.55 < edge_gain(blurred, truth) < 0.7
    # grain the truth lacks raises the mean gradient magnitude a lot, and the gain barely
    grain = truth + rng.normal(0.0, 0.05, truth.shape).astype(np.float32)
    assert sharpness(grain) > 3 * sharpness(truth)
    assert edge_gain(grain, truth) == pytest.approx(1.0, abs=0.05)
    # so a final map that drops an output's grain keeps its true edges: sharpness says 'blurred'
    assert sharpness(truth) / sharpness(grain) < 0.5
    assert edge_gain(truth, truth) / edge_gain(grain, truth) == pytest.approx(1.0, abs=0.05)
    # uint8 RGB reads as its luma in [0, 1]
    rgb = np.repeat((truth * 255).round().astype(np.uint8)[..., None], 3, axis=2)
    assert edge_gain(rgb, truth) == pytest.approx(1.0, abs=0.01)
    assert math.isnan(edge_gain(truth, np.full_like(truth, 0.3)))
    # with a mask, only its pixels count: the blur on the left half, the truth on the right
    cols = np.tile(np.arange(64), (48, 1))
    half = np.where(cols < 24, blurred, truth)
    assert edge_gain(half, truth, cols >= 26) == pytest.approx(1.0)
    assert edge_gain(half, truth, cols < 22) == pytest.approx(edge_gain(blurred, truth, cols < 22))
    assert math.isnan(edge_gain(truth, truth, np.zeros((48, 64), bool)))
    with pytest.raises(ValueError, match="mask must be"):
        edge_gain(truth, truth, np.ones((48, 63), bool))
    with pytest.raises(ValueError, match="one shape"):
        edge_gain(truth, truth[:, :10])
