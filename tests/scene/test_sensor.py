"""Depth losses of real stereo sensors: grazing incidence, dark surfaces, occlusion holes."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gsfix_online.scene import ShipTankConfig, build_scene
from gsfix_online.scene.generate import render_sample
from gsfix_online.scene.sensor import stereo_occlusion, surface_dropout


def test_surface_dropout_follows_incidence_angle() -> None:
    theta = np.linspace(0.0, 89.9, 200)  # columns: incidence angle, deg
    cos = np.broadcast_to(np.cos(np.radians(theta)), (60, 200)).astype(np.float32)
    bright = np.full((60, 200), 128.0, np.float32)
    lost = surface_dropout(cos, bright, 70.0, 0.0, 3.0, np.random.default_rng(0))
    assert not lost[:, theta < 70.0].any()  # never below the grazing angle
    assert lost[:, theta > 80.0].all()  # always 10 deg beyond it
    ramp = lost[:, (theta > 72) & (theta < 78)].mean()
    assert 0.2 < ramp < 0.8
    # Blobs, not salt: a lost pixel's lower neighbour in the ramp is mostly lost too.
    r = lost[:, (theta > 72) & (theta < 78)]
    assert (r[1:] & r[:-1]).sum() / max(r[:-1].sum(), 1) > 0.7


def test_surface_dropout_on_dark_surfaces_only() -> None:
    bright = np.broadcast_to(np.linspace(0.0, 60.0, 120), (40, 120)).astype(np.float32)
    cos = np.ones((40, 120), np.float32)
    lost = surface_dropout(cos, bright, 90.0, 20.0, 2.0, np.random.default_rng(1))
    assert lost[:, bright[0] < 0.5].all() and not lost[:, bright[0] >= 20.0].any()
    none = surface_dropout(cos, bright, 90.0, 0.0, 2.0, np.random.default_rng(1))
    assert not none.any()


def test_stereo_occlusion_is_the_disparity_step_left_of_a_near_object() -> None:
    depth = np.full((10, 80), 2.0, np.float32)  # disparity 50 * 0.1 / 2 = 2.5 px
    depth[:, 30:40] = 1.0  # a near post: disparity 5 px
    lost = stereo_occlusion(depth, fx=50.0, baseline_m=0.1)
    # Background columns 28 and 29 are hidden from the right imager by the post (step 2.5 px).
    assert np.flatnonzero(lost.any(axis=0)).tolist() == [28, 29]
    assert lost[:, [28, 29]].all()
    assert not stereo_occlusion(np.full((5, 20), 2.0, np.float32), 50.0, 0.1).any()
    depth[:, 60] = 0.0  # no surface: never "occluded"
    assert not stereo_occlusion(depth, 50.0, 0.1)[:, 60].any()


def test_structural_losses_in_the_tank_add_to_the_blobs() -> None:
    base = ShipTankConfig(width=64, height=48, n_frames=8, n_novel=0, seed=4, dropout=0.0)
    harsh = replace(base, depth_grazing_deg=60.0, stereo_baseline=0.095)
    a, b = build_scene(base), build_scene(harsh)
    for i in (2, 5):
        sa, sb = render_sample(a, i), render_sample(b, i)
        valid_a, valid_b = sa.depth > 0, sb.depth > 0
        assert not (valid_b & ~valid_a).any()  # losses only remove depth
        assert valid_b.mean() < valid_a.mean() - 0.01
        np.testing.assert_array_equal(sa.depth[valid_b], sb.depth[valid_b])  # same noise draw
        np.testing.assert_array_equal(sa.color, sb.color)
