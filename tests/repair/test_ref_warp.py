"""Reference-view warping against an analytic oracle: a textured plane (and a square occluder in
front of it) ray cast exactly at any pose."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gsfix_online.core.metrics import psnr
from gsfix_online.core.se3 import make_T
from gsfix_online.core.types import FrameError
from gsfix_online.repair.ref_warp import (
    Reference,
    RefWarpConfig,
    ref_warp,
    ref_warp_inpaint,
    select_references,
)

W, H, F = 80, 60, 60.0
K = np.array([[F, 0.0, (W - 1) / 2], [0.0, F, (H - 1) / 2], [0.0, 0.0, 1.0]])
PLANE_Z = 3.0  # metres: the textured wall, facing the cameras at z = 0
OCC_Z, OCC_HALF = 1.5, 0.1  # the occluder: a red square |x|, |y| <= OCC_HALF at z = OCC_Z
RED = (255, 0, 0)
# Bilinear sampling of the wall's 10-pixel sinusoids and 8-bit rounding: measured 45-50 dB
PSNR_EXACT_DB = 35.0


def pose(x: float = 0.0, y: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    a = np.radians(yaw_deg)
    R = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    return make_T(R, [x, y, 0.0])


def texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:  # world metres -> [..., 3] uint8
    ch = [np.sin(2 * np.pi * x / 0.5 + p) * np.cos(2 * np.pi * y / 0.7 - p) for p in (0, 1, 2)]
    return np.clip(np.rint(128 + 80 * np.stack(ch, axis=-1)), 0, 255).astype(np.uint8)


def render(T: np.ndarray, occluder: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Exact colour [H, W, 3] and z-depth [H, W] of the scene at camera-to-world ``T``."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    d = np.stack([(u - K[0, 2]) / F, (v - K[1, 2]) / F, np.ones_like(u)], -1) @ T[:3, :3].T
    c = T[:3, 3]
    t = (PLANE_Z - c[2]) / d[..., 2]  # camera z of d is 1: t is the z-depth
    p = c + t[..., None] * d
    color = texture(p[..., 0], p[..., 1])
    if occluder:
        t_o = (OCC_Z - c[2]) / d[..., 2]
        q = c + t_o[..., None] * d
        hit = (np.abs(q[..., 0]) <= OCC_HALF) & (np.abs(q[..., 1]) <= OCC_HALF) & (t_o > 0)
        t = np.where(hit, t_o, t)
        color[hit] = RED
    return color, t.astype(np.float32)


def ref(T: np.ndarray, occluder: bool = False) -> Reference:
    color, depth = render(T, occluder)
    return Reference(color, depth, K, T)


def warp(T: np.ndarray, refs: list[Reference], occluder: bool = False, **cfg):
    _, depth = render(T, occluder)
    return ref_warp(K, T, depth, np.ones((H, W), bool), W, H, refs, RefWarpConfig(**cfg))


def test_warp_of_a_reference_reproduces_the_view_from_its_exact_depth():
    T_b = pose(0.25, 0.05, yaw_deg=4.0)
    out = warp(T_b, [ref(pose())])
    gt, _ = render(T_b)
    assert out.used == (0,)
    assert 0.8 < out.coverage < 1.0  # the reference's frustum leaves a strip of the view out
    assert psnr(out.image, gt, out.valid) > PSNR_EXACT_DB
    assert (out.image[~out.valid] == 0).all()


def test_identical_pose_is_the_identity_and_gray_references_give_three_channels():
    r = ref(pose(0.1))
    out = warp(pose(0.1), [r])
    assert out.valid.all()
    assert np.abs(out.image.astype(int) - r.color).max() <= 1
    gray = dataclasses.replace(r, color=r.color[..., 1].copy())
    out = warp(pose(0.1), [gray])
    assert out.image.shape == (H, W, 3)
    assert np.abs(out.image.astype(int) - r.color[..., 1:2]).max() <= 1


def hidden_from_origin(T_view: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[H, W] x2: the view's wall points the camera at the origin cannot see for the occluder,
    and the view's points inside that camera's frustum."""
    _, depth = render(T_view, occluder=True)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    d = np.stack([(u - K[0, 2]) / F, (v - K[1, 2]) / F, np.ones_like(u)], -1) @ T_view[:3, :3].T
    p = T_view[:3, 3] + depth[..., None] * d
    on_wall = np.abs(p[..., 2] - PLANE_Z) < 1e-3
    s = OCC_Z / PLANE_Z  # the ray from the origin to p crosses the occluder's plane at s * p
    hidden = on_wall & (np.abs(s * p[..., 0]) <= OCC_HALF) & (np.abs(s * p[..., 1]) <= OCC_HALF)
    u, v = F * p[..., 0] / p[..., 2] + K[0, 2], F * p[..., 1] / p[..., 2] + K[1, 2]
    return hidden, (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)


def test_occluded_points_are_holes_or_come_from_a_reference_that_sees_them():
    T_b, T_c = pose(0.6), pose(-0.6, 0.03)  # C: a sub-pixel shift, not whole pixels
    hidden, in_a = hidden_from_origin(T_b)
    assert hidden.sum() > 30
    gt, _ = render(T_b, occluder=True)
    a = ref(pose(), occluder=True)
    only_a = warp(T_b, [a], occluder=True)
    assert not only_a.valid[hidden].any()
    assert np.array_equal(only_a.valid[~hidden], in_a[~hidden])
    # without the occlusion test the occluder's red is painted on the wall
    blind = warp(T_b, [a], occluder=True, occlusion_tol=1.0)
    assert blind.valid[hidden].all()
    assert (blind.image[hidden] == RED).all(axis=-1).mean() > 0.9
    both = warp(T_b, [a, ref(T_c, occluder=True)], occluder=True)
    assert both.used == (0, 1)
    assert both.valid[hidden].all()
    assert psnr(both.image, gt, hidden) > PSNR_EXACT_DB


def test_holes_stay_holes():
    T = pose(0.1)
    _, depth = render(T)
    depth[:10] = 0.0
    valid = np.ones((H, W), bool)
    valid[:, :7] = False
    out = ref_warp(K, T, depth, valid, W, H, [ref(pose())])
    assert not out.valid[:10].any() and not out.valid[:, :7].any()
    assert (out.image[:10] == 0).all() and (out.image[:, :7] == 0).all()
    assert out.valid[10:, 7:].mean() > 0.9
    empty = ref_warp(K, T, np.zeros((H, W), np.float32), valid, W, H, [ref(pose())])
    assert empty.used == () and not empty.valid.any()
    assert not ref_warp(K, T, depth, valid, W, H, []).valid.any()


def test_references_are_the_k_nearest_that_overlap_the_view():
    refs = [ref(pose(x)) for x in (0.4, 0.1, 0.3, 0.2)]
    refs.append(ref(pose(0.01, yaw_deg=180.0)))  # nearest by position, looking away
    _, depth = render(pose())
    cfg = RefWarpConfig(k=2, rotation_weight_m=0.0)
    assert select_references(K, pose(), depth, refs, cfg) == (1, 3)
    assert select_references(K, pose(), depth, refs, dataclasses.replace(cfg, k=9)) == (1, 3, 2, 0)
    # a reference far to the side holds too little of the view
    far = [ref(pose(3.5)), ref(pose(0.3))]
    assert select_references(K, pose(), depth, far, cfg) == (1,)
    assert select_references(K, pose(), depth, far, dataclasses.replace(cfg, min_overlap=0.0)) == (1, 0)  # fmt: skip


def test_nearer_angle_weighs_more_and_best_takes_one_sample():
    T = pose()
    near, far = ref(pose(0.1)), ref(pose(0.8))
    bright = dataclasses.replace(far, color=np.full_like(far.color, 255))
    mean = warp(T, [near, bright]).image.astype(int)
    exact = warp(T, [near]).image.astype(int)
    inner = (slice(10, 50), slice(10, 50))
    shift = (mean - exact)[inner]
    assert 0 < shift.mean() < 0.5 * (255 - exact[inner]).mean()  # between, nearer the near one
    best = warp(T, [near, bright], blend="best").image.astype(int)
    assert np.abs(best - exact)[inner].max() == 0


def test_inpaint_fills_holes_from_the_mesh_then_telea():
    T = pose(0.1)
    out = warp(T, [ref(pose())])
    assert not out.valid.all()
    mesh = np.full((H, W, 3), 40, np.uint8)
    mesh_valid = np.zeros((H, W), bool)
    mesh_valid[: H // 2] = True
    filled = ref_warp_inpaint(out, mesh, mesh_valid)
    assert np.array_equal(filled[out.valid], out.image[out.valid])
    assert (filled[~out.valid & mesh_valid] == 40).all()
    telea = ~out.valid & ~mesh_valid
    assert telea.any() and (filled[telea] != 0).all()
    gs = np.full((H, W, 3), 200, np.uint8)
    with_gs = ref_warp_inpaint(out, mesh, mesh_valid, gs, np.ones((H, W), np.float32))
    assert (with_gs[~out.valid] == 200).all()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (
            {"view_depth": np.zeros((H, W))},
            r"^view_depth must be float32 \[60, 80\] metres, got float64 \[60, 80\]$",
        ),  # fmt: skip
        (
            {"view_depth": np.zeros((H, W + 1), np.float32)},
            r"^view_depth must be float32 \[60, 80\]",
        ),  # fmt: skip
        (
            {"view_valid": np.ones((H, W), np.uint8)},
            r"^view_valid must be bool \[60, 80\], got uint8",
        ),  # fmt: skip
        (
            {"view_K": np.eye(4)},
            r"^view_K must be a \[3, 3\] intrinsics matrix, got float64 \[4, 4\]$",
        ),  # fmt: skip
        (
            {"view_T_world_cam": np.diag([1.0, 1.0, 2.0, 1.0])},
            r"^view_T_world_cam rotation is not orthonormal",
        ),  # fmt: skip
        ({"width": 0}, r"^width and height must be positive integers, got 0x60$"),
        (
            {"refs": "color"},
            r"^refs\[0\]\.color must be uint8 \[h, w, 3\] or \[h, w\], got float32",
        ),  # fmt: skip
        (
            {"refs": "depth"},
            r"^refs\[0\]\.depth_m must be float32 \[60, 80\] metres, got float32 \[60, 79\]$",
        ),  # fmt: skip
        ({"refs": "K"}, r"^refs\[0\]\.K must be \[\[fx,0,cx\],\[0,fy,cy\],\[0,0,1\]\]"),
    ],
)
def test_bad_inputs_raise_one_line_errors(change, message):
    T = pose()
    color, depth = render(T)
    r = Reference(color, depth, K, T)
    bad_ref = {
        "color": dataclasses.replace(r, color=color.astype(np.float32)),
        "depth": dataclasses.replace(r, depth_m=depth[:, 1:].copy()),
        "K": dataclasses.replace(r, K=-K),
    }
    args = {"view_K": K, "view_T_world_cam": T, "view_depth": depth,
            "view_valid": np.ones((H, W), bool), "width": W, "height": H, "refs": [r]}  # fmt: skip
    args.update(change)
    if isinstance(args["refs"], str):
        args["refs"] = [bad_ref[args["refs"]]]
    with pytest.raises(FrameError, match=message) as err:
        ref_warp(**args)
    assert "\n" not in str(err.value)
