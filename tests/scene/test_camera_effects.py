"""Camera effects: auto-exposure gains and motion blur, against analytic planes and the tank."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from gsfix_online.core.se3 import look_at, make_T
from gsfix_online.core.types import Intrinsics
from gsfix_online.scene import ShipTankConfig, build_scene
from gsfix_online.scene.camera_effects import (
    LUMINANCE,
    blur_sample_count,
    exposure_gains,
    image_motion,
    motion_blur,
    pose_at,
    shutter_ends,
    white_balance_gains,
)
from gsfix_online.scene.generate import render_sample
from gsfix_online.scene.geometry import plane_mesh
from gsfix_online.scene.render import KNEE, Renderer

TOL = {
    "flow_px": 1e-6,  # float64 projection of float32-depth points
    "gain_rel": 0.03,  # 8-bit rounding of the exposed and the ground-truth images, no noise
    # Flow-based blur against 16 averaged renders, as a fraction of the blur itself: measured
    # 0.12 (the gather uses each pixel's own displacement; the slide's parallax varies with depth).
    "blur_vs_renders": 0.25,
}

TINY = ShipTankConfig(width=64, height=48, n_frames=24, n_novel=0, seed=2, image_noise=0.0)


# --------------------------------------------------------------------------------------------
# Exposure
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("step_prob", [0.0, 0.2])
def test_exposure_gains_stay_in_range_and_span_it(step_prob: float) -> None:
    g = exposure_gains(200, 10.0, 0.7, 1.4, 2.0, step_prob, np.random.default_rng(0))
    assert g.shape == (200,) and g.min() >= 0.7 - 1e-12 and g.max() <= 1.4 + 1e-12
    assert g.max() / g.min() > 1.5  # most of the configured 2x range is used
    again = exposure_gains(200, 10.0, 0.7, 1.4, 2.0, step_prob, np.random.default_rng(0))
    np.testing.assert_array_equal(g, again)


def test_exposure_steps_are_sudden_and_wander_is_smooth() -> None:
    smooth = exposure_gains(400, 10.0, 0.7, 1.4, 2.0, 0.0, np.random.default_rng(1))
    stepped = exposure_gains(400, 10.0, 0.7, 1.4, 2.0, 0.05, np.random.default_rng(1))
    jump = lambda g: np.abs(np.diff(np.log(g))).max()  # noqa: E731
    assert jump(smooth) < 0.05  # a few % per frame at most
    assert jump(stepped) > 0.1  # a step of a good part of the range
    np.testing.assert_array_equal(exposure_gains(5, 10, 1.0, 1.0, 2.0, 0.5, None), np.ones(5))  # type: ignore[arg-type]


def test_exposure_scales_frame_light_by_its_gain_and_gt_stays_nominal() -> None:
    cfg = replace(TINY, exposure_gain_min=0.7, exposure_gain_max=1.4)
    scene = build_scene(cfg)
    plain = build_scene(TINY)
    gains = scene.exposure_gains
    assert gains is not None and gains.max() / gains.min() > 1.3
    linear_top = 255 * KNEE ** (1 / 2.2)  # display value where the tone curve leaves linear
    measured = []
    for i in range(0, cfg.n_frames, 3):
        s, p = render_sample(scene, i), render_sample(plain, i)
        np.testing.assert_array_equal(s.color_gt, p.color_gt)  # ground truth at gain 1
        np.testing.assert_array_equal(s.depth, p.depth)  # depth is not the colour camera's
        ok = (s.color_gt > 20) & (s.color < linear_top) & (s.color_gt < linear_top)
        exposed, nominal = ((c[ok].astype(np.float64) / 255) ** 2.2 for c in (s.color, s.color_gt))
        measured.append(exposed.mean() / nominal.mean())
        assert abs(measured[-1] / gains[i] - 1.0) < TOL["gain_rel"], (i, measured[-1], gains[i])
    assert max(measured) / min(measured) > 1.2  # frames really differ in brightness


def test_white_balance_shifts_colour_not_brightness() -> None:
    g = white_balance_gains(300, 10.0, 0.03, 2.0, np.random.default_rng(3))
    np.testing.assert_allclose(g @ LUMINANCE, 1.0, atol=1e-12)
    spread = np.log(g[:, [0, 2]] / g[:, 1:2]).std(axis=0)  # red and blue against green
    assert np.all((spread > 0.02) & (spread < 0.07))  # ~sqrt(2) sigma
    cfg = replace(TINY, white_balance_sigma=0.05, n_frames=12)
    scene = build_scene(cfg)
    assert scene.white_balance is not None and scene.exposure_gains is None
    ratios = []
    for i in (0, 11):
        s = render_sample(scene, i)
        ok = (s.color_gt > 20).all(-1) & (s.color_gt < 200).all(-1)
        seen, nominal = (((c[ok] / 255.0) ** 2.2).mean(0) for c in (s.color, s.color_gt))
        ratios.append(seen / nominal)
        np.testing.assert_allclose(ratios[-1], scene.white_balance[i], rtol=TOL["gain_rel"])
    assert np.abs(ratios[0] - ratios[1]).max() > 0.01
    assert build_scene(replace(cfg, grayscale=True)).white_balance is None  # mono: no AWB


# --------------------------------------------------------------------------------------------
# Motion blur
# --------------------------------------------------------------------------------------------


def _tilted_plane() -> tuple[Renderer, Intrinsics, np.ndarray]:
    """A textured plane filling the view of a camera at the origin: depth ~1.1 m at the left edge,
    ~4.4 m at the right."""
    intr = Intrinsics(40.0, 40.0, 31.5, 23.5, 64, 48)
    corners = [[-2, -3, 0.304], [6, -3, 6.168], [6, 3, 6.168], [-2, 3, 0.304]]  # z = 1.77 + 0.733 x
    return Renderer(plane_mesh(corners)), intr, np.eye(4)


def test_image_motion_of_a_sideways_translation_is_fx_dx_over_z() -> None:
    renderer, intr, T = _tilted_plane()
    r = renderer.render(intr, T)
    dx = np.array([-0.02, 0.0, 0.03])
    samples = np.stack([make_T(np.eye(3), [d, 0.0, 0.0]) for d in dx])
    f = image_motion(r.points, r.mask, intr, T, samples)
    z = r.depth[..., None].astype(np.float64)
    for k, d in enumerate(dx):
        np.testing.assert_allclose(f[k, ..., 0], (-intr.fx * d / z)[..., 0], atol=1e-4)
        np.testing.assert_allclose(f[k, ..., 1], 0.0, atol=TOL["flow_px"])
    assert not f[1].any()  # the reference pose itself: exactly no motion


def test_blur_is_stronger_where_the_image_moves_more() -> None:
    renderer, intr, T = _tilted_plane()
    r = renderer.render(intr, T)
    poses = np.stack([make_T(np.eye(3), [x, 0.0, 0.0]) for x in (-0.08, 0.0, 0.08)])
    flows = image_motion(r.points, r.mask, intr, T, shutter_ends(poses, 1, 1.0))
    n = blur_sample_count(flows, r.mask)
    assert 3 <= n <= 32
    # The plane's own texture changes scale with depth; white noise has the same statistics
    # everywhere in the image, so only the motion differs between the two sides.
    image = np.random.default_rng(0).random(r.radiance.shape).astype(np.float32)
    blurred = motion_blur(image, flows[0], flows[1], n)
    diff = np.abs(blurred - image).mean(axis=-1)  # [H, W]
    extent = np.linalg.norm(flows[1] - flows[0], axis=-1)
    near, far = extent > np.percentile(extent, 75), extent < np.percentile(extent, 25)
    assert extent[near].mean() > 2 * extent[far].mean()  # the near side moves more ...
    assert diff[near].mean() > 1.3 * diff[far].mean()  # ... and is blurred more
    # Along x only: averaging along rows leaves each row's mean (away from the borders) alone.
    inner = (slice(None), slice(12, -12))
    np.testing.assert_allclose(blurred[inner].mean(axis=1), image[inner].mean(axis=1), atol=0.02)
    assert blurred[inner].std() < 0.8 * image[inner].std()


def test_blur_matches_the_average_of_renders_over_the_shutter() -> None:
    """Slow reference: render at 16 poses across the shutter and average the light."""
    renderer, _, T = _tilted_plane()
    intr = Intrinsics(100.0, 100.0, 79.5, 59.5, 160, 120)  # finer pixels: a measurable blur
    c, s = np.cos(0.1), np.sin(0.1)
    step = make_T([[c, 0, s], [0, 1, 0], [-s, 0, c]], [0.05, 0.02, 0.0])  # turn and slide
    poses = np.stack([np.linalg.inv(step), T, step])
    r = renderer.render(intr, T)
    n = 16
    offsets = (np.arange(n) + 0.5) / n - 0.5  # one frame of shutter, in frames
    exact = np.mean([renderer.render(intr, pose_at(poses, 1, a)).radiance for a in offsets], 0)
    flows = image_motion(r.points, r.mask, intr, T, shutter_ends(poses, 1, 1.0))
    approx = motion_blur(r.radiance, flows[0], flows[1], n)
    margin = int(np.ceil(np.abs(flows).max())) + 1  # new content enters at the borders
    inner = (slice(margin, -margin), slice(margin, -margin))
    blur = np.abs(exact - r.radiance)[inner].mean()
    err = np.abs(approx - exact)[inner].mean()
    assert margin < 20
    assert err < TOL["blur_vs_renders"] * blur, (err, blur)


def test_no_motion_no_blur_bit_for_bit() -> None:
    cfg = replace(TINY, shutter_s=0.05)
    scene = build_scene(cfg)
    still = scene.poses.copy()
    still[4:7] = still[5]  # the camera rests for three frames
    sharp_scene = build_scene(TINY)
    blur_scene = replace(scene, poses=still)
    sharp_scene = replace(sharp_scene, poses=still)
    s, p = render_sample(blur_scene, 5), render_sample(sharp_scene, 5)
    np.testing.assert_array_equal(s.color, p.color)
    # A moving frame of the same sequence is blurred.
    m, q = render_sample(blur_scene, 12), render_sample(sharp_scene, 12)
    assert np.abs(m.color.astype(int) - q.color.astype(int)).mean() > 0.5


def test_blur_grows_with_camera_speed_along_the_path() -> None:
    """The path eases in from rest: frame 0 barely moves, mid-path frames move most."""
    cfg = replace(TINY, shutter_s=0.05)
    blur, sharp = build_scene(cfg), build_scene(TINY)
    speed = np.linalg.norm(np.diff(blur.poses[:, :3, 3], axis=0), axis=1)
    d = []
    for i in (0, int(np.argmax(speed))):
        a, b = render_sample(blur, i), render_sample(sharp, i)
        d.append(np.abs(a.color.astype(int) - b.color.astype(int)).mean())
    assert d[1] > 3 * d[0]


def test_shutter_ends_are_centred_and_held_at_the_sequence_ends() -> None:
    poses = np.stack([look_at([x, 0.0, 0.0], [x, 1.0, 0.0]) for x in (0.0, 0.1, 0.2)])
    ends = shutter_ends(poses, 1, 0.5)
    np.testing.assert_allclose(ends[:, 0, 3], [0.075, 0.125], atol=1e-12)
    first = shutter_ends(poses, 0, 0.5)
    np.testing.assert_array_equal(first[0], poses[0])  # before the first frame: at rest
    np.testing.assert_allclose(first[1][0, 3], 0.025, atol=1e-12)
    np.testing.assert_array_equal(pose_at(poses, 2, 0.3), poses[2])
