"""Mesh fill and Telea inpainting baselines."""

from __future__ import annotations

import numpy as np
import pytest

from gsfix_online.repair.baselines import (
    fill_and_inpaint,
    gs_inpaint,
    inpaint,
    inpaint_telea,
    mesh_fill,
)


def test_mesh_fill_takes_gs_where_opaque_mesh_elsewhere_and_reports_missing():
    gs = np.full((4, 6, 3), 200, np.uint8)
    mesh = np.full((4, 6, 3), 50, np.uint8)
    alpha = np.ones((4, 6), np.float32)
    alpha[:, 3:] = 0.1
    valid = np.ones((4, 6), bool)
    valid[:, 5] = False
    r = mesh_fill(gs, alpha, mesh, valid)
    assert (r.image[:, :3] == 200).all() and (r.image[:, 3:5] == 50).all()
    assert (r.image[:, 5] == 200).all()  # neither covers: the 3DGS value stays, marked missing
    assert r.missing.sum() == 4 and r.missing[:, 5].all()


def test_telea_fills_missing_from_surroundings_only():
    img = np.full((20, 20), 120, np.uint8)
    missing = np.zeros((20, 20), bool)
    missing[8:12, 8:12] = True
    img[missing] = 0
    out = inpaint_telea(img, missing)
    assert np.abs(out[missing].astype(int) - 120).max() <= 2
    assert np.array_equal(out[~missing], img[~missing])
    assert np.array_equal(inpaint_telea(img, np.zeros_like(missing)), img)


def test_gs_inpaint_keeps_the_opaque_render_and_fills_its_holes_from_it_alone():
    gs = np.full((20, 20, 3), 160, np.uint8)
    alpha = np.ones((20, 20), np.float32)
    alpha[6:14, 6:14] = 0.3  # a hole of the map: black, nearly transparent
    gs[alpha < 0.5] = 0
    out = gs_inpaint(gs, alpha)
    assert np.array_equal(out[alpha >= 0.5], gs[alpha >= 0.5])
    assert np.abs(out[alpha < 0.5].astype(int) - 160).max() <= 2  # from the render around it
    assert np.array_equal(gs_inpaint(gs, alpha, alpha_min=0.2), gs)  # 0.3 covers at 0.2
    with pytest.raises(ValueError, match="gs_alpha must be float"):
        gs_inpaint(gs, alpha > 0.5)


def test_mesh_fill_rejects_mismatched_shapes():
    gs = np.zeros((4, 6, 3), np.uint8)
    with pytest.raises(ValueError, match="mesh_color must match"):
        mesh_fill(
            gs, np.ones((4, 6), np.float32), np.zeros((4, 6), np.uint8), np.ones((4, 6), bool)
        )
    with pytest.raises(ValueError, match="gs_alpha must be float"):
        mesh_fill(gs, np.ones((4, 6), np.uint8), gs, np.ones((4, 6), bool))


def _gradient_with_hole(channels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A smooth colour gradient (truth), the same with a black 10x12 hole, and the hole."""
    yy, xx = np.mgrid[0:40, 0:48].astype(np.float64)
    planes = [40 + 3 * xx + yy, 200 - 2 * yy, 60 + xx + 2 * yy][:channels]
    truth = np.rint(np.stack(planes, -1) if channels > 1 else planes[0]).astype(np.uint8)
    hole = np.zeros((40, 48), bool)
    hole[14:24, 18:30] = True
    img = truth.copy()
    img[hole] = 0
    return truth, img, hole


@pytest.mark.parametrize("method", ["telea", "ns", "fsr"])
@pytest.mark.parametrize("channels", [1, 3])
def test_each_method_fills_a_smooth_gradient_far_better_than_black(method, channels):
    truth, img, hole = _gradient_with_hole(channels)
    out = inpaint(img, hole, method)
    assert out.dtype == np.uint8 and out.shape == img.shape
    assert np.array_equal(out[~hole], img[~hole])  # known pixels are kept exactly
    err = np.abs(out.astype(int) - truth.astype(int))[hole]  # [N(, C)] levels
    black = np.abs(img.astype(int) - truth.astype(int))[hole]
    assert black.mean() > 120
    # measured mean error, levels (gray / colour): telea 3.7 / 3.1, ns 2.8 / 2.4, fsr 0.2 / 0.6
    assert err.mean() < {"telea": 5.0, "ns": 4.0, "fsr": 1.0}[method]
    if channels == 3:  # each channel filled from its own plane: RGB order kept through FSR's BGR
        assert (err.reshape(-1, 3).mean(axis=0) < 5).all()


@pytest.mark.parametrize("method", ["telea", "ns", "fsr"])
def test_single_channel_images_keep_their_shape(method):
    _, img, hole = _gradient_with_hole(1)
    out = inpaint(img[..., None], hole, method)
    assert out.shape == (40, 48, 1) and out.dtype == np.uint8
    np.testing.assert_array_equal(out[..., 0], inpaint(img, hole, method))


def test_nothing_or_everything_missing_returns_the_image():
    _, img, hole = _gradient_with_hole(3)
    for m in (np.zeros_like(hole), np.ones_like(hole)):
        out = inpaint(img, m, "fsr")
        assert np.array_equal(out, img) and out is not img


@pytest.mark.parametrize(
    ("image", "missing", "method", "match"),
    [
        (np.zeros((4, 6, 3), np.uint16), np.zeros((4, 6), bool), "ns",
         r"^image must be uint8 \[H, W\] or \[H, W, 1\|3\], got uint16 \[4, 6, 3\]$"),
        (np.zeros((4, 6, 2), np.uint8), np.zeros((4, 6), bool), "fsr",
         r"^image must be uint8 .*, got uint8 \[4, 6, 2\]$"),
        (np.zeros((4, 6, 3), np.uint8), np.zeros((4, 5), bool), "fsr",
         r"^missing must be bool \[4, 6\], got bool \[4, 5\]$"),
        (np.zeros((4, 6, 3), np.uint8), np.zeros((4, 6), np.uint8), "ns",
         r"^missing must be bool \[4, 6\], got uint8 \[4, 6\]$"),
        (np.zeros((4, 6, 3), np.uint8), np.zeros((4, 6), bool), "shiftmap",
         r"^inpainting method must be one of \['telea', 'ns', 'fsr'\], got 'shiftmap'$"),
    ],
)  # fmt: skip
def test_bad_input_raises_one_line_errors(image, missing, method, match):
    with pytest.raises(ValueError, match=match):
        inpaint(image, missing, method)


def test_fill_and_inpaint_gives_mesh_fill_and_each_method():
    truth, gs, hole = _gradient_with_hole(3)
    alpha = (~hole).astype(np.float32)
    mesh = np.zeros_like(gs)
    out = fill_and_inpaint(gs, alpha, mesh, np.zeros_like(hole), ("ns", "fsr"))
    assert list(out) == ["mesh_fill", "ns", "fsr"]
    assert np.array_equal(out["mesh_fill"], gs)  # the mesh hit nothing: the hole stays
    for m in ("ns", "fsr"):
        np.testing.assert_array_equal(out[m], inpaint(gs, hole, m))


@pytest.mark.parametrize(("h", "w"), [(4, 5), (40, 41), (61, 83)])
def test_fsr_fills_the_last_partial_block_and_tiny_images(h, w):
    # OpenCV's FSR alone leaves these pixels black (it fills whole 16x16 blocks only)
    img = np.full((h, w, 3), 200, np.uint8)
    hole = np.zeros((h, w), bool)
    hole[h - 1, w - 1] = hole[h - 1, w // 2] = hole[h // 2, w - 1] = hole[0, 0] = True
    img[hole] = 0
    out = inpaint(img, hole, "fsr")
    assert (out[hole] == 200).all() and np.array_equal(out[~hole], img[~hole])
