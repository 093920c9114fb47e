"""Keyframe selection (new Gaussians, depth and alpha overlap) and the bounded store's eviction."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from gsfix_online.core.se3 import make_T
from gsfix_online.core.types import Intrinsics, RGBDFrame, make_frame
from gsfix_online.mapping.splat.keyframes import (
    KeyframeConfig,
    KeyframeStore,
    alpha_overlap,
    depth_overlap,
    initialize_state,
    prior_images,
    select_keyframe,
)

W, H, F, Z = 64, 48, 50.0, 2.0
K = Intrinsics(F, F, (W - 1) / 2, (H - 1) / 2, W, H)
FOV_W_M = W / F * Z  # width of the plane z = 2 seen by the camera: 2.56 m


def plane_frame(
    x: float = 0.0, yaw_deg: float = 0.0, gray: bool = False, depth: float = Z
) -> RGBDFrame:
    """A camera at (x, 0, 0) looking along +z (turned by yaw about y) at the plane world z = 2."""
    a = math.radians(yaw_deg)
    R = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    T = make_T(R, [x, 0.0, 0.0])
    # depth of the plane z_world = 2 along each pixel ray
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([(u - K.cx) / F, (v - K.cy) / F, np.ones_like(u, float)], -1) @ R.T
    with np.errstate(divide="ignore"):
        t = np.where(rays[..., 2] > 1e-6, depth / rays[..., 2], 0.0)
    z_cam = t  # the ray's camera z-component is 1, so the parameter t is the z-depth
    shape = (H, W) if gray else (H, W, 3)
    return make_frame(np.full(shape, 100, np.uint8), z_cam.astype(np.float32), K, T, 0)


def test_depth_overlap_analytic() -> None:
    ref = plane_frame()
    assert depth_overlap(ref, ref, stride_px=1) == 1.0
    # shifted by half the field of view: half the samples stay in view
    half = depth_overlap(plane_frame(x=FOV_W_M / 2), ref, stride_px=1)
    assert half == pytest.approx(0.5, abs=1 / W)
    assert depth_overlap(plane_frame(x=2 * FOV_W_M), ref) == 0.0
    # a surface at another depth is not the same surface
    assert depth_overlap(plane_frame(depth=3.0), ref) == 0.0
    empty = plane_frame(depth=-1.0)  # no valid depth at all
    assert math.isnan(depth_overlap(empty, ref))


def test_alpha_overlap() -> None:
    a = np.zeros((H, W), np.float32)
    a[:, : W // 4] = 0.9
    assert alpha_overlap(a, 0.5) == 0.25


def test_selection_by_new_gaussians_and_overlap() -> None:
    cfg = KeyframeConfig(min_new_gaussians=50, min_overlap=0.7, overlap_stride_px=2)
    state = initialize_state()
    d = select_keyframe(plane_frame(), 0, state, cfg)
    assert (d.is_keyframe, d.reason) == (True, "first") and math.isnan(d.overlap)
    d = select_keyframe(plane_frame(x=0.1), 49, state, cfg)
    assert (d.is_keyframe, d.reason) == (False, "none") and d.overlap > 0.9
    d = select_keyframe(plane_frame(x=0.1), 50, state, cfg)
    assert (d.is_keyframe, d.reason) == (True, "new_gaussians")
    # drift slowly: overlap is measured against the last keyframe (x = 0.1), not the last frame
    xs = 0.1 + np.arange(1, 20) * 0.1
    decisions = [select_keyframe(plane_frame(x=float(x)), 0, state, cfg) for x in xs]
    first = next(i for i, dd in enumerate(decisions) if dd.is_keyframe)
    assert decisions[first].reason == "low_overlap"
    assert decisions[first].overlap < 0.7 <= decisions[first - 1].overlap
    # the shift to the keyframe is then about (1 - 0.7) of the field of view
    assert xs[first] - 0.1 == pytest.approx(0.3 * FOV_W_M, abs=0.1 + 2 * 2 * Z / F)
    assert state.n_frames == 3 + len(xs) and state.n_keyframes >= 3


def test_selection_by_alpha_and_without_depth() -> None:
    cfg = KeyframeConfig(overlap_from="alpha", min_overlap=0.5, min_new_gaussians=0)
    state = initialize_state()
    select_keyframe(plane_frame(), 0, state, cfg, alpha=np.ones((H, W), np.float32))
    covered = torch.ones(H, W)
    covered[:, : W // 2 + 1] = 0.0
    d = select_keyframe(plane_frame(), 1000, state, cfg, alpha=covered)
    assert (d.reason, d.overlap) == (
        "low_overlap",
        pytest.approx((W // 2 - 1) / W),
    )  # min_new 0 = off
    # depth mode, a frame without valid depth: judged by new Gaussians alone
    cfg = KeyframeConfig()
    state = initialize_state()
    select_keyframe(plane_frame(), 0, state, cfg)
    assert not select_keyframe(plane_frame(depth=-1.0), 0, state, cfg).is_keyframe


def _at(frame: RGBDFrame, stamp_s: float) -> RGBDFrame:
    return make_frame(frame.color, frame.depth, frame.intrinsics, frame.T_world_cam,
                      round(stamp_s * 1e9))  # fmt: skip


def test_spacing_rules_make_keyframes_of_a_slow_trajectory() -> None:
    """A camera that creeps keeps its overlap: overlap alone makes one keyframe, the spacing
    rules one per interval, distance, angle or share, and each names its reason."""

    def run(cfg: KeyframeConfig, frames: list[RGBDFrame]) -> list[tuple[int, str]]:
        state = initialize_state()
        out = [(i, select_keyframe(f, 0, state, cfg).reason) for i, f in enumerate(frames)]
        return [(i, r) for i, r in out if r != "none"]

    base = dict(min_new_gaussians=0, min_overlap=0.7, overlap_stride_px=2)
    still = [_at(plane_frame(), 0.1 * i) for i in range(30)]  # 3 s at 10 Hz, not moving
    assert run(KeyframeConfig(**base), still) == [(0, "first")]
    assert run(KeyframeConfig(**base, max_interval_s=1.0), still) == [
        (0, "first"), (10, "interval"), (20, "interval"),
    ]  # fmt: skip
    creep = [_at(plane_frame(x=0.02 * i), 0.1 * i) for i in range(30)]  # 2 cm a frame
    assert run(KeyframeConfig(**base), creep) == [(0, "first")]  # overlap stays above 0.7
    assert run(KeyframeConfig(**base, max_translation_m=0.2), creep) == [
        (0, "first"), (10, "moved"), (20, "moved"),
    ]  # fmt: skip
    turn = [_at(plane_frame(yaw_deg=1.5 * i), 0.1 * i) for i in range(12)]  # 1.5 deg a frame
    assert run(KeyframeConfig(**base, max_rotation_deg=5.9), turn)[:3] == [
        (0, "first"), (4, "turned"), (8, "turned"),
    ]  # fmt: skip
    # the share: at least a quarter of the frames seen so far are keyframes
    shared = run(KeyframeConfig(**base, min_share=0.25), still)
    assert [i for i, _ in shared] == [0, 4, 8, 12, 16, 20, 24, 28]
    assert {r for _, r in shared[1:]} == {"share"}
    # overlap still fires first where it applies
    far = [plane_frame(), plane_frame(x=2 * FOV_W_M)]
    assert run(KeyframeConfig(**base, min_share=1.0), far) == [(0, "first"), (1, "low_overlap")]


def test_share_rule_only_on_a_slow_path() -> None:
    """With ``share_below_step_m`` the share rule fires while the path's mean pose distance per
    frame (translation + ``rotation_weight_m`` x angle) is under it: a creeping camera gets every
    other frame, a fast one only its overlap keyframes, and a path that starts still and speeds
    up gets share keyframes until its mean passes the threshold."""

    def run(gate_m: float, frames: list[RGBDFrame]) -> list[tuple[int, str]]:
        cfg = KeyframeConfig(min_new_gaussians=0, min_overlap=0.7, overlap_stride_px=2,
                             min_share=0.5, share_below_step_m=gate_m)  # fmt: skip
        state = initialize_state()
        out = [(i, select_keyframe(f, 0, state, cfg).reason) for i, f in enumerate(frames)]
        return [(i, r) for i, r in out if r != "none"]

    every_other = [(0, "first")] + [(i, "share") for i in range(2, 20, 2)]
    slow = [_at(plane_frame(x=0.02 * i), 0.1 * i) for i in range(20)]  # 2 cm a frame
    fast = [_at(plane_frame(x=0.1 * i), 0.1 * i) for i in range(20)]  # 10 cm a frame
    assert run(0.05, slow) == every_other
    assert run(0.05, fast) == [(0, "first"), (8, "low_overlap"), (16, "low_overlap")]
    assert run(0.0, fast) == every_other  # 0: no gate
    # rotation counts: 3 degrees a frame in place is 0.5 m/rad x 0.052 rad = 2.6 cm a frame
    turn = [_at(plane_frame(yaw_deg=3.0 * i), 0.1 * i) for i in range(20)]
    assert run(0.05, turn) == every_other
    assert {r for _, r in run(0.02, turn)} == {"first", "low_overlap"}
    # still for 6 frames, then 10 cm a frame: the mean over the path passes 5 cm at frame 10
    ease = [_at(plane_frame(x=max(0.0, 0.1 * (i - 5))), 0.1 * i) for i in range(20)]
    assert run(0.05, ease) == every_other[:5] + [(16, "low_overlap")]


def test_selection_validation() -> None:
    state = initialize_state()
    with pytest.raises(ValueError, match="overlap_from is 'alpha' but no alpha was given"):
        select_keyframe(plane_frame(), 0, state, KeyframeConfig(overlap_from="alpha"))
    with pytest.raises(ValueError, match=r"alpha must be \[48, 64\], got \[48, 64, 1\]"):
        select_keyframe(
            plane_frame(), 0, state, KeyframeConfig(overlap_from="alpha"), alpha=np.ones((H, W, 1))
        )
    with pytest.raises(ValueError, match="n_new_gaussians must be a non-negative int"):
        select_keyframe(plane_frame(), -1, state, KeyframeConfig())


def test_store_bound_and_eviction_keeps_coverage() -> None:
    store = KeyframeStore(capacity=4)
    for x in (0.0, 1.0, 2.0, 3.0):
        _, ev = store.add(plane_frame(x=x))
        assert ev is None
    kf, ev = store.add(plane_frame(x=3.01))  # near-duplicate of x = 3: the older copy goes
    assert len(store) == 4 and ev is not None and ev.kf_id == 3
    assert store.ids == [0, 1, 2, 4] and store.latest is kf
    _, ev = store.add(plane_frame(x=3.02))  # the newest is never evicted
    assert ev.kf_id == 4 and store.ids == [0, 1, 2, 5]
    # rotation counts: a turned camera at the same place is not redundant
    store = KeyframeStore(capacity=3, rotation_weight_m=1.0)
    for x, yaw in ((0.0, 0.0), (0.0, 90.0), (1.0, 0.0)):
        store.add(plane_frame(x=x, yaw_deg=yaw))
    _, ev = store.add(plane_frame(x=1.2))
    assert ev.kf_id == 2 and store.n_evicted == 1


def test_repaired_views_and_input_keyframes_are_bounded_apart() -> None:
    """A repaired view next to an input keyframe does not evict it (the store used to, one
    input keyframe per repaired view, the one nearest the view); each kind evicts its own most
    redundant, and the bound survives a snapshot (an old one without it gets the default)."""
    import dataclasses

    from gsfix_online.mapping.splat.views import REPAIRED_FRAME_ID

    def repaired(x: float) -> RGBDFrame:
        return dataclasses.replace(plane_frame(x=x), frame_id=REPAIRED_FRAME_ID)

    store = KeyframeStore(capacity=3, repaired_capacity=2)
    for x in (0.0, 1.0, 2.0):
        store.add(plane_frame(x=x))
    for x in (2.01, 1.01):  # each right beside an input keyframe
        assert store.add(repaired(x))[1] is None
    assert store.ids == [0, 1, 2, 3, 4]
    _, ev = store.add(repaired(1.02))  # a third repaired view: the older of 1.01, 1.02 goes
    assert ev is not None and ev.kf_id == 4 and store.ids == [0, 1, 2, 3, 5]
    _, ev = store.add(plane_frame(x=0.01))  # a fourth input keyframe: the older of 0, 0.01
    assert ev is not None and ev.kf_id == 0 and store.ids == [1, 2, 3, 5, 6]
    state = store.state_dict()
    assert KeyframeStore.from_state_dict(state).repaired_capacity == 2
    del state["repaired_capacity"]
    assert KeyframeStore.from_state_dict(state).repaired_capacity == 64
    with pytest.raises(ValueError, match="repaired_capacity must be an int >= 2"):
        KeyframeStore(4, repaired_capacity=1)


def test_store_renders_sample_and_validation() -> None:
    store = KeyframeStore.from_config(KeyframeConfig(capacity=10))
    for i in range(5):
        store.add(
            plane_frame(x=float(i), gray=True),
            np.full((H, W, 1), 0.5, np.float32),
            torch.ones(H, W),
            7,
        )
    kf = store[2]
    assert kf.render.shape == (H, W, 1) and kf.alpha.dtype == np.float32 and kf.n_new_gaussians == 7
    store.update_render(2, np.zeros((H, W, 1), np.float32), np.zeros((H, W), np.float32))
    assert store[2].render.max() == 0.0
    a = store.sample(3, np.random.default_rng(0))
    b = store.sample(3, np.random.default_rng(0))
    assert [k.kf_id for k in a] == [k.kf_id for k in b] and len(a) == 3
    assert all(k.kf_id != 4 for k in store.sample(10, np.random.default_rng(1)))
    assert len(store.sample(10, np.random.default_rng(1), exclude_latest=False)) == 5
    with pytest.raises(ValueError, match=r"render must be \[48, 64, 1\], got \[48, 64, 3\]"):
        store.add(
            plane_frame(gray=True), np.zeros((H, W, 3), np.float32), np.zeros((H, W), np.float32)
        )
    with pytest.raises(ValueError, match="render and alpha must be given together"):
        store.add(plane_frame(), np.zeros((H, W, 3), np.float32))
    with pytest.raises(KeyError, match="no keyframe 99"):
        store[99]
    with pytest.raises(ValueError, match="capacity must be an int >= 2"):
        KeyframeStore(1)


def test_store_keeps_a_prior_through_render_updates_and_its_state() -> None:
    store = KeyframeStore(4)
    store.add(plane_frame(), np.full((H, W, 3), 0.5, np.float32), np.ones((H, W), np.float32))
    assert store[0].prior is None and prior_images(store[0], H, W) is None
    prior = np.zeros((H // 2, W // 2, 4), np.float32)  # the training resolution
    prior[:, : W // 4, :3] = 0.8  # the map predicted the left half
    prior[:, : W // 4, 3] = 1.0
    store.set_prior(0, prior)
    store.update_render(0, np.zeros((H, W, 3), np.float32), np.zeros((H, W), np.float32))
    kf = store[0]
    assert kf.render.max() == 0.0 and kf.prior is not None  # a new render keeps the prior
    color, alpha = prior_images(kf, H, W)  # at the frame's size, bilinear
    assert color.shape == (H, W, 3) and alpha.shape == (H, W)
    assert color[:, :30].min() == pytest.approx(0.8) and color[:, 34:].max() == 0.0
    assert alpha[:, :30].min() == 1.0 and alpha[:, 34:].max() == 0.0
    assert 0.0 < alpha[0, W // 2 - 1] < 1.0  # the border blends
    # a snapshot keeps it; one taken before priors were kept restores none
    state = store.state_dict()
    np.testing.assert_array_equal(KeyframeStore.from_state_dict(state)[0].prior, prior)
    old = {
        **state,
        "items": [{k: v for k, v in it.items() if k != "prior"} for it in state["items"]],
    }
    assert KeyframeStore.from_state_dict(old)[0].prior is None
    with pytest.raises(
        ValueError, match=r"prior must be \[h, w, 4\] \(colour, alpha\), got \[24, 32, 3\]"
    ):
        store.set_prior(0, prior[..., :3])
