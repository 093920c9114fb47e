"""PSNR and SSIM on analytic pairs, and their input checks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gsfix_online.inspection.metrics import psnr, scores, ssim


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
